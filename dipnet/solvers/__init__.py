"""Reconstruction solvers behind one interface (:class:`Solver`)."""

from __future__ import annotations

import difflib

from dipnet.core.keywords import accepted_keywords
from dipnet.solvers.base import Solver, measured_profiles
from dipnet.solvers.deep_image_prior import DeepImagePriorSolver
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.minnorm import LSMRSolver, LSQRSolver, MinNormSolver
from dipnet.solvers.optimize import OptimisationSolver
from dipnet.solvers.voxel import VoxelSolver

SOLVERS: dict[str, type[Solver]] = {
    "minnorm": MinNormSolver,
    "lsqr": LSQRSolver,
    "lsmr": LSMRSolver,
    "voxel": VoxelSolver,
    "implicit": ImplicitSolver,
    "dip": DeepImagePriorSolver,
}


def make_solver(name: str, **options) -> Solver:
    """The solver called ``name`` (a key of :data:`SOLVERS`) built with ``options``.

    Raises:
        ValueError: an unknown ``name``.
        TypeError: options the solver does not take, naming the closest it takes (a misspelling) or the solvers
            that take them (an option of another solver), and its options."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; choose one of {sorted(SOLVERS)}")
    check_solver_options(name, options)
    return SOLVERS[name](**options)


def check_solver_options(name: str, options: dict) -> None:
    """Refuse ``options`` that the solver called ``name`` (a key of :data:`SOLVERS`) does not take.

    Raises:
        TypeError: as :func:`make_solver`, naming the closest option it takes or the solvers that take them."""
    takes = accepted_keywords(SOLVERS[name])
    unknown = sorted(set(options) - (takes or set(options)))
    if unknown:
        hints = []
        for option in unknown:
            close = difflib.get_close_matches(option, sorted(takes), n=1)
            owners = [other for other, cls in SOLVERS.items() if option in (accepted_keywords(cls) or ())]
            hints.append(f"{option} (did you mean {close[0]}?)" if close else
                         f"{option} (an option of {', '.join(owners)})" if owners else option)
        raise TypeError(f"the {name} solver takes no option(s) {'; '.join(hints)}; its options: "
                        f"{', '.join(sorted(takes))}")


__all__ = ["DeepImagePriorSolver", "ImplicitSolver", "LSMRSolver", "LSQRSolver", "MinNormSolver", "OptimisationSolver",
           "SOLVERS", "VoxelSolver", "Solver", "check_solver_options", "make_solver", "measured_profiles"]
