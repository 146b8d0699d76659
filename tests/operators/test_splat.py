"""The splatting backend (dipnet.operators.splat): its explicit sparse matrix, planes per slab, a single voxel's hat
kernel, a ball's slab volumes against the analytic ones, several planes per slab."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.operators import SplatOperator
from dipnet.operators.analytic import ball_occupancy
from dipnet.operators import make_operator
from dipnet.operators.splat import plane_slab_weights

from operator_problems import generic_directions, random_problem


def test_splat_sparse_matrix_equals_operator():
    grid, dirs, x, gen = random_problem(3, seed=4)
    op = SplatOperator(grid, dirs, 20)
    mat = op.to_sparse()
    np.testing.assert_allclose(mat @ x.reshape(-1).numpy(), op(x).reshape(-1).numpy(), rtol=1e-12, atol=1e-9)
    y = torch.rand(op.profile_shape, generator=gen, dtype=torch.float64)
    np.testing.assert_allclose(mat.T @ y.reshape(-1).numpy(), op.adjoint(y).reshape(-1).numpy(), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("n_slabs", [16, 8, 10, 11, 47, 64])
def test_each_voxel_layer_is_shared_between_the_slabs_it_overlaps(n_slabs):
    grid = Grid(32, 3, extent=96.0)  # 3 mm voxel layers
    weights = plane_slab_weights(grid, n_slabs)  # (32, M)
    torch.testing.assert_close(weights.sum(1), torch.ones(32, dtype=torch.float64))
    # the layers' shares of each slab add up to its thickness in voxels
    torch.testing.assert_close(weights.sum(0), torch.full((n_slabs,), 32 / n_slabs, dtype=torch.float64))
    if 32 % n_slabs == 0:  # a whole number of layers per slab: each layer in one slab
        assert set(weights.unique().tolist()) == {0.0, 1.0}
    assert plane_slab_weights(grid, 32) is None  # planes and slabs coincide


@pytest.mark.parametrize("n_slabs", [20, 30, 36, 47, 72])
def test_a_dip_along_a_grid_axis_is_right_for_any_number_of_slabs(n_slabs):
    """A dip along z, x or y sees whole voxel layers at one height: with slabs of another thickness than a voxel
    each layer must be shared by overlap (sharing it at its centre height gave profile errors of 13.6% at 20
    slabs and 141% at 72 on a 24^3 ball). Now the error is the voxelisation's own, as for a tilted dip and
    the Fourier backend, and splat and rotate_sum stay one operator."""
    grid, r = Grid(24, 3, 100.0), 0.9 * 50.0
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.5, 0.75**0.5]], dtype=torch.float64)
    occ = ball_occupancy(grid, torch.zeros(3, dtype=torch.float64), r, 7)
    op = SplatOperator(grid, dirs, n_slabs)
    prof = op(occ)
    edges = op.slab_edges().clamp(-r, r)
    cap = math.pi * (r**2 * edges - edges**3 / 3)
    error = (prof - (cap[1:] - cap[:-1])).norm(dim=1) / (cap[1:] - cap[:-1]).norm()
    fourier = make_operator(grid, dirs, n_slabs, backend="fourier")(occ)
    assert float(error.max()) < 0.05
    assert float(((prof[:2] - fourier[:2]).norm(dim=1) / fourier[:2].norm(dim=1)).max()) < 2e-3
    torch.testing.assert_close(make_operator(grid, dirs, n_slabs, backend="rotate_sum")(occ), prof)


def test_a_single_voxel_lands_on_its_height_with_a_hat_kernel():
    """One voxel alone: its volume goes to at most two neighbouring slabs, in full, and the slab centres weighted
    by the profile give back its height t = x . theta (a hat kernel keeps the first moment)."""
    grid = Grid(16, 3, extent=32.0)
    theta = generic_directions(5, 3)
    op = SplatOperator(grid, theta)  # one plane per slab: the planes are the slab centres
    edges = op.slab_edges()
    mids = (edges[1:] + edges[:-1]) / 2
    inside = torch.nonzero(grid.working_mask().reshape(-1)).squeeze(1)
    picked = inside[torch.randperm(inside.numel(), generator=torch.Generator().manual_seed(0))[:20]]
    vols = torch.zeros(len(picked), grid.n**3, dtype=torch.float64)
    vols[torch.arange(len(picked)), picked] = 1.0
    prof = op(vols.reshape(-1, *grid.shape))  # (20, K, M): one voxel per volume
    torch.testing.assert_close(prof.sum(-1), torch.full((20, 5), grid.voxel_volume, dtype=torch.float64))
    hit = prof > 0
    first, last = hit.double().argmax(-1), grid.n - 1 - hit.flip(-1).double().argmax(-1)
    assert bool((last - first <= 1).all()) and bool((hit.sum(-1) == (last - first + 1)).all())
    heights = grid.centers().reshape(-1, 3)[picked] @ theta.T  # (20, K)
    torch.testing.assert_close((prof * mids).sum(-1) / grid.voxel_volume, heights)


def test_a_ball_gives_the_analytic_slab_volumes():
    """A centred ball of radius r: slab [a, b] holds pi (r^2 t - t^3 / 3) between a and b (clipped to +-r), along
    every direction (the voxelisation's error only: measured 7.5e-3 relative at 32^3)."""
    grid, r = Grid(32, 3, 100.0), 30.0
    op = SplatOperator(grid, generic_directions(4, 3))
    prof = op(ball_occupancy(grid, torch.zeros(3, dtype=torch.float64), r))
    edges = op.slab_edges().clamp(-r, r)
    cap = math.pi * (r**2 * edges - edges**3 / 3)
    exact = cap[1:] - cap[:-1]
    assert float(((prof - exact).norm(dim=1) / exact.norm()).max()) < 1.5e-2
    torch.testing.assert_close(prof.sum(1), torch.full((4,), 4 / 3 * math.pi * r**3, dtype=torch.float64), rtol=1e-3,
                               atol=0.0)


def test_several_planes_per_slab_keep_the_volume_and_the_adjoint():
    """Slabs about three voxels thick (several sampling planes each): every profile still sums to the masked volume, and
    the adjoint is the transpose: <A x, y> = <x, A^T y>."""
    grid, dirs, x, gen = random_problem(3, seed=7)
    op = SplatOperator(grid, dirs, n_slabs=8)
    assert op.slab_weights.shape == (grid.n, 8)
    volume = float((x * grid.working_mask()).sum()) * grid.voxel_volume
    torch.testing.assert_close(op(x).sum(1), torch.full((len(dirs),), volume, dtype=torch.float64))
    y = torch.rand(op.profile_shape, generator=gen, dtype=torch.float64)
    lhs, rhs = float((op(x) * y).sum()), float((x * op.adjoint(y)).sum())
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
