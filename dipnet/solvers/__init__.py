"""Reconstruction solvers behind one interface (:class:`Solver`)."""

from __future__ import annotations

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
    """The solver called ``name`` (a key of :data:`SOLVERS`) built with ``options``."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; choose one of {sorted(SOLVERS)}")
    return SOLVERS[name](**options)


__all__ = ["DeepImagePriorSolver", "ImplicitSolver", "LSMRSolver", "LSQRSolver", "MinNormSolver", "OptimisationSolver", "SOLVERS", "VoxelSolver", "Solver", "make_solver", "measured_profiles"]
