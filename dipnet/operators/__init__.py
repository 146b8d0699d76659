"""Dip operator backends behind one interface (:class:`DipOperator`)."""

from __future__ import annotations

import math

import torch

from dipnet.core.grid import Grid, as_grid
from dipnet.operators.base import DipOperator
from dipnet.operators.fourier import FourierOperator
from dipnet.operators.rotate_sum import RotateSumOperator
from dipnet.operators.splat import SplatOperator
from dipnet.core.keywords import accepted_keywords, forwards_to

BACKENDS: dict[str, type[DipOperator]] = {
    "rotate_sum": RotateSumOperator,
    "splat": SplatOperator,
    "fourier": FourierOperator,
}

#: Other names of backends: ``grid_sample`` is the design's name of the reference operator.
ALIASES: dict[str, str] = {"grid_sample": "rotate_sum"}

#: Backends whose linear map is exactly an explicit sparse matrix (``splat.to_sparse()``):
#: rotate_sum pushes each voxel to its trilinear neighbours and sums planes, which gives the
#: splat numbers to rounding (tests/contracts/test_operators_contract.py).
SPLAT_MATRIX_BACKENDS = ("splat", "rotate_sum")

DEFAULT_BACKEND = "auto"

# Measured crossover (scripts/bench_operator.py, forward + adjoint on 2 cores): the cached
# splat wins while K * N^d stays below about 2e6 voxel-orientation pairs, fourier beyond.
AUTO_SPLAT_LIMIT = 2_000_000


def select_backend(grid: Grid, n_orientations: int) -> str:
    """The fastest backend that meets the operator contract for ``K`` orientations on ``grid``."""
    return "splat" if n_orientations * math.prod(grid.shape) <= AUTO_SPLAT_LIMIT else "fourier"


@forwards_to(*BACKENDS.values())
def make_operator(grid: Grid, directions: torch.Tensor, n_slabs: int | None = None,
                  backend: str = DEFAULT_BACKEND, **options) -> DipOperator:
    """Build the dip operator ``backend`` (a name in :data:`BACKENDS` or :data:`ALIASES`, or
    ``"auto"``: :func:`select_backend`) for ``grid`` and ``directions`` ``(K, d)``.

    The operator's ``auto_selected`` attribute says whether ``"auto"`` chose it (a solver may
    then use another backend of the same contract, and says so in its ``info``).

    Raises:
        ValueError: an unknown backend, or ``options`` the backend does not take (with ``"auto"``, the
            backend it chose for this problem size: ``eps`` is the fourier backend's, which small problems
            do not use; the message names the backends that take them)."""
    grid = as_grid(grid)
    auto = backend == "auto"
    backend = ALIASES.get(backend, backend)
    if auto:
        backend = select_backend(grid, len(directions))
    if backend not in BACKENDS:
        raise ValueError(f"unknown operator backend {backend!r}; choose auto, one of {sorted(BACKENDS)} "
                         f"or an alias {sorted(ALIASES)}")
    unknown = sorted(set(options) - (accepted_keywords(BACKENDS[backend]) or set(options)))
    if unknown:
        owners = [name for name, cls in BACKENDS.items() if set(unknown) <= (accepted_keywords(cls) or set())]
        chose = (f"backend='auto' chose {backend} for {len(directions)} orientations on a {grid.n}^{grid.ndim} grid "
                 f"(K N^d {'<=' if backend == 'splat' else '>'} {AUTO_SPLAT_LIMIT:,}), and " if auto else "")
        fix = f"choose backend={owners[0]!r} to set them" if owners else "remove them"
        raise ValueError(f"{chose}the {backend} backend takes no option(s) {', '.join(unknown)} "
                         f"(backends that take them: {', '.join(owners) or 'none'}): {fix}")
    operator = BACKENDS[backend](grid, directions, n_slabs, **options)
    operator.auto_selected = auto
    return operator


def backend_name(operator: DipOperator) -> str:
    """The :data:`BACKENDS` name of ``operator``'s class."""
    for name, cls in BACKENDS.items():
        if type(operator) is cls:
            return name
    raise ValueError(f"operator type {type(operator).__name__} is not a registered backend")


__all__ = ["ALIASES", "AUTO_SPLAT_LIMIT", "BACKENDS", "SPLAT_MATRIX_BACKENDS", "backend_name", "DEFAULT_BACKEND",
           "DipOperator", "FourierOperator", "RotateSumOperator", "SplatOperator", "make_operator", "select_backend"]
