"""The shape protocol (dipnet.shapes.base): the shared occupancy sampler (partial volumes by supersampling,
analytic answers on a toy cube), the default bounds, notes and warnings, and the checks of
volume_below's arguments."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.shapes.base import Shape, ShapeError, ShapeWarning, check_dips, check_radius, check_supersample


class Square(Shape):
    """An axis-aligned cube (square in 2D) of half-side ``a`` mm centred on the origin; ``volume_below`` exact
    for axis directions only (enough for these tests)."""

    def __init__(self, a: float, ndim: int = 3) -> None:
        self.name, self.ndim, self.a, self.notes = "square", ndim, a, []
        self.volume = (2 * a) ** ndim

    def contains(self, points: np.ndarray) -> np.ndarray:
        return np.all(np.abs(points) <= self.a, axis=1)

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        d, t = check_dips(directions, heights, self.ndim)
        return torch.from_numpy(np.clip(t[None, :] + self.a, 0, 2 * self.a) * (2 * self.a) ** (self.ndim - 1)
                                * np.ones((len(d), 1)))

    def radius(self) -> float:
        return self.a * math.sqrt(self.ndim)


def test_a_voxel_aligned_cube_fills_its_voxels_exactly():
    grid = Grid(8, 3, extent=16.0)  # 2 mm voxels
    occ = Square(4.0).occupancy(grid)
    assert occ.dtype == torch.float32 and occ.shape == grid.shape
    assert float(occ.sum()) * grid.voxel_volume == Square(4.0).volume  # 4^3 voxels of 8 mm^3
    assert set(torch.unique(occ).tolist()) == {0.0, 1.0}


@pytest.mark.parametrize("s", [1, 2, 4])
def test_supersampling_gives_partial_volumes(s):
    """A square of half-side 3 mm on 2 mm pixels: its edges cut the border pixels in half. Sampling s^2 points
    per pixel counts them as 1/2 when s is even; s = 1 tests the centres only (which lie inside)."""
    grid = Grid(8, 2, extent=16.0)
    occ = Square(3.0, ndim=2).occupancy(grid, supersample=s)
    area = float(occ.sum()) * grid.voxel_volume
    assert area == pytest.approx(36.0 if s > 1 else 64.0)
    assert float(occ[4, 4]) == 1.0 and float(occ[4, 2]) == (0.5 if s > 1 else 1.0) and float(occ[4, 1]) == 0.0


def test_the_default_bounds_are_the_radius_box():
    lo, hi = Square(2.0, ndim=2).bounds()
    np.testing.assert_allclose(lo, [-2 * math.sqrt(2)] * 2)
    np.testing.assert_allclose(hi, [2 * math.sqrt(2)] * 2)
    assert Square(1.0).dip_bytes_per_reading() > 0


def test_a_grid_of_the_wrong_dimension_or_a_bad_supersample_is_named():
    with pytest.raises(ShapeError, match="shape 'square' is 3D but the grid is 2D"):
        Square(1.0).occupancy(Grid(8, 2))
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="supersample must be a positive integer"):
            Square(1.0).occupancy(Grid(8, 3), supersample=bad)


@pytest.mark.parametrize("bad", [0, -1, 1.5, float("nan"), float("inf"), True, "2"])
def test_check_supersample_refuses_anything_but_a_whole_number_from_one(bad):
    with pytest.raises(ValueError, match="supersample must be a positive integer"):
        check_supersample(bad)
    assert check_supersample(3) == 3 and check_supersample(np.int64(2)) == 2 and check_supersample(2.0) == 2


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), True, "abc", None])
def test_check_radius_refuses_anything_but_a_finite_positive_number(bad):
    """shape.radius=abc or null failed as "shape: an option of the wrong type ('>' not supported ...)": the
    radius was compared, not checked."""
    with pytest.raises(ShapeError, match=r"shape radius must be a finite, positive number \(mm\), got "):
        check_radius(bad)
    assert check_radius(3) == 3.0 and type(check_radius(np.float32(2.5))) is float


def test_a_repair_is_noted_and_warned():
    shape = Square(1.0)
    with pytest.warns(ShapeWarning, match="holes filled"):
        shape._warn("holes filled")
    assert shape.notes == ["holes filled"]


def test_dip_arguments_are_checked_and_returned_as_float64():
    d, t = check_dips(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float32), [1, 2, 3], 3)
    assert d.dtype == t.dtype == np.float64 and d.shape == (1, 3) and t.tolist() == [1.0, 2.0, 3.0]
    for directions, heights, message in (
            (np.ones((2, 2)), np.zeros(3), r"directions must have shape \(K, 3\)"),
            (np.eye(3), np.zeros((3, 1)), r"heights must have shape \(H,\)"),
            (2 * np.eye(3), np.zeros(3), "directions must be unit vectors")):
        with pytest.raises(ValueError, match=message):
            check_dips(directions, heights, 3)
    below = Square(2.0).volume_below(torch.eye(3)[2:], torch.tensor([-3.0, 0.0, 3.0]))
    torch.testing.assert_close(below, torch.tensor([[0.0, 32.0, 64.0]], dtype=torch.float64))
