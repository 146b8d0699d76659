"""Dip operator backends behind one interface (:class:`DipOperator`)."""

from __future__ import annotations

import math

import torch

from dipnet.grid import Grid
from dipnet.operators.base import DipOperator
from dipnet.operators.fourier import FourierOperator
from dipnet.operators.rotate_sum import RotateSumOperator
from dipnet.operators.splat import SplatOperator

BACKENDS: dict[str, type[DipOperator]] = {
    "rotate_sum": RotateSumOperator,
    "splat": SplatOperator,
    "fourier": FourierOperator,
}

DEFAULT_BACKEND = "auto"

# Measured crossover (scripts/bench_operator.py, forward + adjoint on 2 cores): the cached
# splat wins while K * N^d stays below about 2e6 voxel-orientation pairs, fourier beyond.
AUTO_SPLAT_LIMIT = 2_000_000


def select_backend(grid: Grid, n_orientations: int) -> str:
    """The fastest backend that meets the operator contract for ``K`` orientations on ``grid``."""
    return "splat" if n_orientations * math.prod(grid.shape) <= AUTO_SPLAT_LIMIT else "fourier"


def make_operator(grid: Grid, directions: torch.Tensor, n_slabs: int | None = None,
                  backend: str = DEFAULT_BACKEND, **options) -> DipOperator:
    """Build the dip operator ``backend`` (a name in :data:`BACKENDS`, or ``"auto"``:
    :func:`select_backend`) for ``grid`` and ``directions`` ``(K, d)``."""
    if backend == "auto":
        backend = select_backend(grid, len(directions))
    if backend not in BACKENDS:
        raise ValueError(f"unknown operator backend {backend!r}; choose auto or one of {sorted(BACKENDS)}")
    return BACKENDS[backend](grid, directions, n_slabs, **options)


__all__ = ["AUTO_SPLAT_LIMIT", "BACKENDS", "DEFAULT_BACKEND", "DipOperator", "FourierOperator", "RotateSumOperator",
           "SplatOperator", "make_operator", "select_backend"]
