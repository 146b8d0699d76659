"""support_hull by column intervals: the same mask as testing every voxel against every slab."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.solvers.optimize import slab_support, support_hull
from dipnet.solvers.voxel import VoxelSolver


def brute_force_hull(target, grid, directions, edges, rel_tol, margin):
    """The reference: every voxel centre tested against every orientation's slab range."""
    lo, hi = slab_support(target, edges, rel_tol, margin * grid.voxel_size)
    t = grid.centers(target.dtype).reshape(-1, grid.ndim) @ directions.to(target.dtype).T  # (voxels, K)
    inside = ((t >= lo) & (t <= hi)).all(dim=1).reshape(grid.shape)
    return inside & grid.working_mask()


def directions_with_flat_ones(ndim: int, k: int, seed: int) -> torch.Tensor:
    """Random unit directions plus the axes and directions with no last component (theta_z = 0)."""
    gen = torch.Generator().manual_seed(seed)
    rand = torch.randn(k, ndim, generator=gen, dtype=torch.float64)
    flat = torch.randn(3, ndim, generator=gen, dtype=torch.float64)
    flat[:, -1] = 0.0
    axes = torch.cat([torch.eye(ndim, dtype=torch.float64), -torch.eye(ndim, dtype=torch.float64)])
    dirs = torch.cat([rand, flat, axes])
    return dirs / dirs.norm(dim=1, keepdim=True)


def ball_profiles(grid: Grid, directions: torch.Tensor, centre: torch.Tensor, radius: float, m: int):
    """Slab volumes ``(K, m)`` of a ball (exact slab integrals of its cross-section) and the edges."""
    edges = torch.linspace(-grid.extent / 2, grid.extent / 2, m + 1, dtype=torch.float64)
    offset = directions @ centre  # (K,) the ball's centre height per direction
    u = (edges[None, :] - offset[:, None]).clamp(-radius, radius)  # heights relative to the centre
    if grid.ndim == 3:  # volume below height u: pi (r^2 u - u^3/3)
        below = math.pi * (radius**2 * u - u**3 / 3)
    else:  # area below u: u sqrt(r^2 - u^2) + r^2 asin(u / r)
        below = u * (radius**2 - u**2).clamp(min=0).sqrt() + radius**2 * torch.asin(u / radius)
    return below.diff(dim=1), edges


@pytest.mark.parametrize("ndim,n,margin", [(2, 40, 1.5), (2, 33, 0.0), (3, 20, 1.5), (3, 17, 3.0)])
def test_column_hull_equals_the_brute_force_mask(ndim, n, margin):
    grid = Grid(n, ndim, 100.0)
    dirs = directions_with_flat_ones(ndim, 25, seed=n)
    centre = torch.tensor([8.0, -5.0, 3.0][:ndim], dtype=torch.float64)
    target, edges = ball_profiles(grid, dirs, centre, 22.0, m=n)
    expected = brute_force_hull(target, grid, dirs, edges, 0.005, margin)
    for chunk in (None, 1, 7):
        got = support_hull(target, grid, dirs, edges, 0.005, margin, chunk=chunk)
        assert torch.equal(got, expected)
    assert 0 < int(expected.sum()) < int(grid.working_mask().sum())  # the slabs did cut the ball


def test_a_flat_direction_that_misses_a_column_empties_it():
    # theta = +x only: the slab support [lo, hi] in x keeps whole columns inside it and none outside
    grid = Grid(16, 3, 100.0)
    dirs = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    edges = torch.linspace(-50, 50, 17, dtype=torch.float64)
    target = torch.zeros(1, 16, dtype=torch.float64)
    target[0, 6:9] = 1.0  # material between x = -12.5 and 6.25 mm
    hull = support_hull(target, grid, dirs, edges, 0.005, margin=0.0)
    x = grid.axis()
    keep = (x >= edges[6]) & (x <= edges[9])
    assert torch.equal(hull, keep[None, None, :].expand(grid.shape) & grid.working_mask())


def test_a_solver_given_dips_that_share_no_voxel_says_so():
    """Profiles that put the object in two places at once (up: 20-25 mm above the centre; down: 20-25 mm
    below it, as far-off start heights do): the support hull is empty; one named error, no ZeroDivisionError."""
    from dipnet.core.measurement import DipMeasurement
    from dipnet.operators import make_operator
    from dipnet.solvers.optimize import EmptySupportError

    grid = Grid(16, extent=60.0)
    profiles = np.zeros((2, 16))
    profiles[:, 13:15] = 100.0  # slabs at 22.5-30 mm along each direction
    m = DipMeasurement(directions=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), profiles=profiles,
                       slab_thickness=grid.voxel_size, offsets=np.full(2, -30.0))
    with pytest.raises(EmptySupportError, match="calibrate the rig geometry"):
        VoxelSolver(iterations=5, progress=False).solve(m, make_operator(grid, m.directions, grid.n))
