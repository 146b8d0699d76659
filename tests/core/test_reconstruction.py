"""Reconstructions: the binary volume is the occupancy above the threshold; the saved file holds both."""

import numpy as np
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
    """Before: Reconstruction(numpy_array, grid).binary (and evaluate on it) failed with "AttributeError: 'numpy.ndarray'
    object has no attribute 'detach'"."""
    grid = Grid(8, 2, 40.0)
    occupancy = np.linspace(0, 1, 64, dtype=np.float32).reshape(grid.shape)
    recon = Reconstruction(occupancy, grid, threshold=0.5)
    assert isinstance(recon.occupancy, torch.Tensor) and recon.occupancy.dtype == torch.float32
    assert np.array_equal(recon.binary, occupancy > 0.5)
