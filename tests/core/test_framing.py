"""Grid framing: the object keeps its size in mm at every resolution; a saved measurement's extent."""

import numpy as np
import pytest

from dipnet.core.framing import extent_around, measurement_extent, smallest_fill
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere

@pytest.mark.parametrize("n", [16, 24, 40, 96])
def test_the_object_fills_its_share_of_the_working_ball(n):
    extent = extent_around(30.0, n, 0.9)
    working_radius = extent * (n - 2) / (2 * n)  # half the side less one voxel
    assert working_radius * 0.9 == pytest.approx(30.0)
    assert Grid(n, 3, extent).radius == pytest.approx(working_radius)

def test_bad_radius_or_fill_are_refused():
    with pytest.raises(ValueError, match="radius must be positive"):
        extent_around(0.0, 16, 0.9)
    with pytest.raises(ValueError, match=r"fill must be in \(0, 1\]"):
        extent_around(10.0, 16, 1.5)

@pytest.mark.parametrize("ndim", [2, 3])
def test_at_the_smallest_fill_the_object_holds_one_voxel(ndim):
    radius, volume, n = 30.0, 5000.0, 16
    fill = smallest_fill(radius, volume, n, ndim)
    assert Grid(n, ndim, extent_around(radius, n, fill)).voxel_volume == pytest.approx(volume)

def test_a_saved_measurement_knows_its_extent_and_other_files_do_not(tmp_path):
    k, m = 4, 10
    offsets = np.array([-40.0, -40.0, -35.0, -30.0])  # the farthest slab edge: -40 or -30 + 10 * 7 = 40
    DipMeasurement(fibonacci_hemisphere(k), np.ones((k, m)), 7.0, offsets).save(tmp_path / "m.npz")
    assert measurement_extent(tmp_path / "m.npz") == pytest.approx(2 * max(40.0, -30.0 + 70.0))
    assert measurement_extent(tmp_path / "scan.jsonl") is None


def test_a_dip_with_a_wrong_offset_is_named_not_framed(tmp_path):
    """The audit's case: one dip's offset 1000 mm off made a grid 60 times too large and a shape of
    2e7 mm^3 from 3e4 measured, with exit 0. A dip whose volume sits off the rigid object's c . theta is named."""
    from dipnet.shapes import Ball
    from dipnet.simulator.simulate import simulate_measurement

    grid = Grid(24, 3, 80.0)
    _, m = simulate_measurement(Ball(20.0, center=(5.0, -3.0, 2.0)), fibonacci_hemisphere(40), grid=grid)
    m.save(tmp_path / "good.npz")
    assert measurement_extent(tmp_path / "good.npz") < 100.0  # an off-centre ball is one rigid object
    m.offsets[5] += 1000.0
    m.save(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match=r"dip\(s\) \[5\] lie far from"):
        measurement_extent(tmp_path / "bad.npz")
