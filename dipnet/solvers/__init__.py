"""Reconstruction solvers behind one interface (:class:`Solver`)."""

from dipnet.solvers.base import Solver, measured_profiles

__all__ = ["Solver", "measured_profiles"]
