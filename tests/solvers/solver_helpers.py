"""Helpers shared by the optimisation-solver tests."""

from __future__ import annotations

import itertools

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import make_operator
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere


# Noise-free data the grid reproduces exactly: the "auto" weight rule reads the profiles' own curvature
# as noise there and raises the TV weight (docs/guide/solvers.md, limits), so recovery tests fix it.
FIXED_TV = {"tv": {"weight": 1e-3}}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small problems run faster on one thread, and the test machine is shared."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def partial_volume(grid: Grid, inside, sub: int = 3) -> torch.Tensor:
    """Occupancy fractions of an analytic solid ``inside(points (..., d) mm) -> bool``, float64."""
    centres, acc = grid.centers(), torch.zeros(grid.shape, dtype=torch.float64)
    for s in itertools.product(range(sub), repeat=grid.ndim):
        acc += inside(centres + ((torch.tensor(s, dtype=torch.float64) + 0.5) / sub - 0.5) * grid.voxel_size)
    return acc / sub**grid.ndim


def hollow_ellipsoid(p: torch.Tensor) -> torch.Tensor:
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return ((x / 32) ** 2 + (y / 22) ** 2 + (z / 16) ** 2 < 1) & ((x - 8) ** 2 + (y + 4) ** 2 + (z - 2) ** 2 >= 81)


def noise_free_problem(ndim: int, inside_2d):
    """``(truth occupancy, operator, noise-free measurement)``: 48^2 with 6 angles (``inside_2d``)
    or the hollow ellipsoid at 24^3 with 20 directions."""
    if ndim == 2:
        grid, dirs, inside = Grid(48, 2), directions_2d(angles_2d(6, start_deg=10.0)), inside_2d
    else:
        grid, dirs, inside = Grid(24, 3), fibonacci_hemisphere(20), hollow_ellipsoid
    truth = partial_volume(grid, inside)
    op = make_operator(grid, dirs, backend="splat")
    with torch.no_grad():
        profiles = op(truth)
    k = op.n_orientations
    return truth, op, DipMeasurement(op.directions, profiles, op.slab_thickness, op.slab_edges()[:1].expand(k))


def perturbed_denoiser(scale: float, seed: int = 0):
    """A 2-channel :class:`~dipnet.solvers.denoiser.OccupancyDenoiser` whose weights are moved by
    ``scale`` standard normals, so it is not the identity an untrained one is."""
    from dipnet.solvers.denoiser import OccupancyDenoiser

    torch.manual_seed(seed)
    net = OccupancyDenoiser(channels=2)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(scale * torch.randn_like(p))
    return net
