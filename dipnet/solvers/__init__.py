"""Reconstruction solvers behind one interface (:class:`Solver`)."""

from dipnet.solvers.base import Solver, measured_profiles
from dipnet.solvers.minnorm import LSMRSolver, LSQRSolver, MinNormSolver

__all__ = ["LSMRSolver", "LSQRSolver", "MinNormSolver", "Solver", "measured_profiles"]
