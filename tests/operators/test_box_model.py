"""The box-voxel model: one voxel's profile is the distribution of a sum of uniforms; volume is conserved."""

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators.box_model import box_voxel_profiles


def test_a_voxel_seen_along_an_axis_fills_exactly_its_slab():
    grid = Grid(8, 3, 8.0)  # 1 mm voxels; 8 slabs of 1 mm: slab edges on voxel faces
    volume = torch.zeros(grid.shape, dtype=torch.float64)
    volume[4, 4, 4] = 1.0  # the voxel at (x, y, z) = (0.5, 0.5, 0.5) mm
    profile = box_voxel_profiles(grid, torch.tensor([[0.0, 0.0, 1.0]]), 8, volume)[0]
    expected = torch.zeros(8, dtype=torch.float64)
    expected[4] = grid.voxel_volume
    assert torch.allclose(profile, expected, atol=1e-12)


def test_every_direction_conserves_the_volume():
    grid = Grid(10, 3, 20.0)
    volume = torch.rand(grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    profiles = box_voxel_profiles(grid, fibonacci_hemisphere(7), 12, volume)
    inside = float((volume.reshape(-1)[grid.working_mask().reshape(-1)]).sum()) * grid.voxel_volume
    assert torch.allclose(profiles.sum(dim=1), torch.full((7,), inside, dtype=torch.float64), rtol=1e-10)
    assert float(profiles.min()) >= -1e-12


def test_a_diagonal_view_spreads_a_voxel_over_several_slabs():
    grid = Grid(8, 3, 8.0)
    volume = torch.zeros(grid.shape, dtype=torch.float64)
    volume[4, 4, 4] = 1.0
    d = torch.tensor([[1.0, 1.0, 0.0]]) / 2**0.5
    profile = box_voxel_profiles(grid, d, 16, volume)[0]
    peak = int(profile.argmax())
    assert profile.sum() == pytest.approx(1.0)
    assert torch.count_nonzero(profile > 1e-12) >= 2 and profile[peak] < 1.0
