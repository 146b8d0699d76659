"""Small dip-operator problems shared by the operator contract (tests/contracts) and the per-backend tests
(tests/operators): generic orientations, random volumes, a relative error."""

from __future__ import annotations

import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere


def generic_directions(k: int, ndim: int) -> torch.Tensor:
    """Generic test orientations (no grid axis), ``(k, ndim)``."""
    return fibonacci_hemisphere(k) if ndim == 3 else directions_2d(angles_2d(k, start_deg=7.0))


def rel_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """``|a - b| / |b|`` (Frobenius norms)."""
    return float((a - b).norm() / b.norm())


def random_problem(ndim: int, seed: int = 0):
    """``(grid, directions, volume, generator)``: a uniform random float64 volume on a 24^3 (3D) or 40^2 (2D)
    grid, 6 generic orientations, and the seeded generator for further draws."""
    grid = Grid(24 if ndim == 3 else 40, ndim)
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(grid.shape, generator=gen, dtype=torch.float64)
    return grid, generic_directions(6, ndim), x, gen
