"""Reconstructions: the binary volume is the occupancy above the threshold; the saved file holds both."""

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.reconstruction import Reconstruction


def test_the_binary_volume_is_the_occupancy_above_the_threshold_and_round_trips(tmp_path):
    grid = Grid(8, 3, 40.0)
    occupancy = torch.linspace(0, 1, 8**3, dtype=torch.float64).reshape(grid.shape)
    recon = Reconstruction(occupancy, grid, threshold=0.25)
    assert recon.binary.sum() == int((occupancy > 0.25).sum())
    recon.save(tmp_path / "r.npz", extra_map=np.ones(grid.shape))
    with np.load(tmp_path / "r.npz") as saved:
        assert np.allclose(saved["occupancy"], occupancy.numpy(), atol=1e-7)
        assert np.array_equal(saved["binary"], recon.binary) and float(saved["threshold"]) == 0.25
        assert (int(saved["grid_n"]), int(saved["grid_ndim"]), float(saved["grid_extent"])) == (8, 3, 40.0)
        assert str(saved["axis_order"]) == "zyx" and saved["extra_map"].shape == grid.shape


def test_a_numpy_occupancy_is_taken_as_a_tensor():
    """Before: Reconstruction(numpy_array, grid).binary (and evaluate on it) failed with
    "AttributeError: 'numpy.ndarray' object has no attribute 'detach'"."""
    grid = Grid(8, 2, 40.0)
    occupancy = np.linspace(0, 1, 64, dtype=np.float32).reshape(grid.shape)
    recon = Reconstruction(occupancy, grid, threshold=0.5)
    assert isinstance(recon.occupancy, torch.Tensor) and recon.occupancy.dtype == torch.float32
    assert np.array_equal(recon.binary, occupancy > 0.5)


def test_a_result_made_by_hand_must_lie_on_its_grid():
    """Before: an occupancy of another shape was accepted and check_consistency failed with a torch RuntimeError ("The
    size of tensor a (10) must match ..."); a NaN threshold gave an empty binary volume; a resolution was taken for a
    grid."""
    grid = Grid(8, 3, 40.0)
    with pytest.raises(ValueError, match=r"occupancy has shape \(10, 10, 10\), but Grid\(n=8.*holds \(8, 8, 8\)"):
        Reconstruction(torch.zeros(10, 10, 10), grid)
    with pytest.raises(ValueError, match="threshold must be a number"):
        Reconstruction(torch.zeros(grid.shape), grid, threshold=float("nan"))
    with pytest.raises(TypeError, match="grid must be a dipnet.Grid"):
        Reconstruction(torch.zeros(grid.shape), 8)
    assert Reconstruction(torch.zeros(grid.shape), grid, threshold=np.float32(0.25)).threshold == 0.25
