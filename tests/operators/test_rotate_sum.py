"""The reference backend (dipnet.operators.rotate_sum): its rotated frames, layer sums along a grid axis, results
that do not depend on the chunking, the splat's numbers."""

from __future__ import annotations

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.operators import RotateSumOperator, SplatOperator
from dipnet.operators.rotate_sum import orthonormal_frame

from operator_problems import generic_directions, random_problem, rel_error


@pytest.mark.parametrize("ndim", (2, 3))
def test_frames_are_orthonormal_and_their_last_axis_is_theta(ndim):
    """Generic directions and both helper branches (near the x axis and away from it), unnormalised input; the 3D
    frames are right-handed (in 2D only the axis along theta matters: the other is its perpendicular)."""
    theta = generic_directions(6, ndim)
    if ndim == 3:
        theta = torch.cat([theta, torch.tensor([[1.0, 0.0, 0.0], [0.95, 0.3, 0.1], [0.0, 0.0, 1.0]],
                                               dtype=torch.float64)])
    frames = orthonormal_frame(3.0 * theta)
    eye = torch.eye(ndim, dtype=torch.float64).expand(len(theta), ndim, ndim)
    torch.testing.assert_close(frames @ frames.transpose(1, 2), eye)
    if ndim == 3:
        torch.testing.assert_close(torch.linalg.det(frames), torch.ones(len(theta), dtype=torch.float64))
    torch.testing.assert_close(frames[:, -1], theta / theta.norm(dim=1, keepdim=True))


@pytest.mark.parametrize("ndim", (2, 3))
def test_along_a_grid_axis_each_slab_is_a_layer_of_voxels(ndim):
    """theta = the last grid axis, one slab per voxel layer: slab j holds the masked volume of layer j exactly
    (the volume's axis 0 runs along the last coordinate)."""
    grid = Grid(12, ndim, extent=24.0)
    axis = torch.zeros(1, ndim, dtype=torch.float64)
    axis[0, -1] = 1.0
    x = torch.rand(grid.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    prof = RotateSumOperator(grid, axis)(x)
    layers = (x * grid.working_mask()).reshape(grid.n, -1).sum(1) * grid.voxel_volume
    torch.testing.assert_close(prof[0], layers)


def test_chunking_changes_nothing():
    """Orientations rotated one at a time, or 4 at a time with a short last chunk, give the same forward and
    adjoint as all at once."""
    grid, dirs, x, gen = random_problem(3, seed=8)
    y = torch.rand(len(dirs), grid.n, generator=gen, dtype=torch.float64)
    ops = [RotateSumOperator(grid, dirs, chunk=c) for c in (1, 4, len(dirs))]
    for op in ops[:2]:
        torch.testing.assert_close(op(x), ops[2](x), rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(op.adjoint(y), ops[2].adjoint(y), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n_slabs", (None, 8))
def test_the_splat_computes_the_same_numbers(n_slabs):
    """The splat's claim: rotation by trilinear pushes then plane sums = a hat kernel on the voxel heights, also
    with several sampling planes per slab (8 slabs of 3 voxels)."""
    grid, dirs, x, _ = random_problem(3, seed=9)
    ref = RotateSumOperator(grid, dirs, n_slabs)(x)
    assert rel_error(SplatOperator(grid, dirs, n_slabs)(x), ref) < 1e-12


@pytest.mark.parametrize("chunk", [0, -1, 2.5, True])
def test_a_chunk_that_is_no_positive_whole_number_is_refused(chunk):
    """Before: 0 "range() arg 3 must not be zero", -1 "torch.cat(): expected a non-empty list of Tensors", 2.5 and
    ``True`` cut to 2 and 1, naming no option."""
    with pytest.raises(ValueError, match=r"chunk \(orientations rotated at once\) must be a whole number"):
        RotateSumOperator(Grid(8, 3), generic_directions(2, 3), chunk=chunk)
