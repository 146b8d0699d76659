"""simulate_measurement end to end: physics -> RawScan -> preprocessing -> DipMeasurement round trips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import make_operator
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.simulator.physics import Balance, LevelSensor, Tank
from dipnet.core.rawscan import read_rawscan
from dipnet.shapes import Ball, Disk, builtin_shape
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.base import measured_profiles

GRID3 = Grid(32, 3, 100.0)
GRID2 = Grid(64, 2, 100.0)
DIRS3 = fibonacci_hemisphere(12)
DIRS2 = directions_2d(angles_2d(10))
SHAPES = {
    "ball": (Ball(40.0, (3.0, -2.0, 1.0)), GRID3, DIRS3),
    "chamber_box": (builtin_shape("chamber_box", 3, 0.9 * GRID3.radius), GRID3, DIRS3),
    "disk": (Disk(40.0, (2.0, 1.0)), GRID2, DIRS2),
    "chamber_box_2d": (builtin_shape("chamber_box", 2, 0.9 * GRID2.radius), GRID2, DIRS2),
}


def _exact_slabs(shape, dirs, grid: Grid) -> np.ndarray:
    """Slab volumes from the true geometry at the operator's slab edges, ``(K, N)``."""
    edges = torch.linspace(-grid.extent / 2, grid.extent / 2, grid.n + 1, dtype=torch.float64)
    return np.diff(shape.volume_below(dirs, edges).numpy(), axis=1)


@pytest.mark.parametrize("name", list(SHAPES))
@pytest.mark.parametrize("quantum", [0.0, 0.01])
def test_noise_free_round_trip_recovers_slab_volumes(name, quantum):
    shape, grid, dirs = SHAPES[name]
    raw, m = simulate_measurement(shape, dirs, grid=grid, sensor=LevelSensor(quantum_mm=quantum), progress=False)
    err = np.abs(m.profiles.numpy() - _exact_slabs(shape, dirs, grid)).max()
    assert err < 0.01 * shape.volume  # the requirement: within 1% of the object volume
    sums = m.profiles.sum(1).numpy()
    # Archimedes: every profile sums to the volume (up to one level quantum x A)
    np.testing.assert_allclose(sums, shape.volume, rtol=1e-9,
                               atol=quantum * raw.header.tank_cross_section_mm2 + 1e-9 * shape.volume)
    assert raw.complete_orientations() == list(range(len(dirs)))


@pytest.mark.parametrize("name", ["ball", "chamber_box"])
def test_matches_the_operator_on_the_occupancy(name):
    """The simulator measures the geometry, the operator a 32^3 voxelisation: close, not equal."""
    shape, grid, dirs = SHAPES[name]
    _, m = simulate_measurement(shape, dirs, grid=grid, progress=False)
    op = make_operator(grid, dirs, grid.n)
    predicted = op(shape.occupancy(grid, supersample=4).double())
    assert np.abs((m.profiles - predicted).numpy()).max() < 0.02 * shape.volume
    assert torch.linalg.norm(m.profiles - predicted) < 0.08 * torch.linalg.norm(predicted)
    assert torch.equal(measured_profiles(m, op), m.profiles)  # no resampling needed: same slabs
    np.testing.assert_allclose(m.directions.numpy(), op.directions.numpy(), atol=1e-12)


def test_two_dimensional_units():
    """In 2D the tank cross-section is a width (mm) and the profiles are areas (mm^2)."""
    shape, grid, dirs = SHAPES["disk"]
    raw, m = simulate_measurement(shape, dirs, grid=grid, tank=Tank(cross_section_mm2=250.0),
                                  sensor=LevelSensor(quantum_mm=0.0), progress=False)
    o = raw.orientations[0]
    assert raw.header.units["tank_cross_section"] == "mm"
    assert o.values[-1] - o.values[0] == pytest.approx(shape.volume / 250.0)
    assert m.profiles.sum(1).numpy() == pytest.approx(np.full(len(dirs), shape.volume))


def test_balance_smoothing_step_and_default_edges():
    shape, grid, dirs = SHAPES["ball"]
    _, m = simulate_measurement(shape, dirs, grid=grid, sensor=Balance(quantum_g=0.0), step_mm=2.0,
                                smooth=True, progress=False)
    assert m.profiles.sum(1).numpy() == pytest.approx(np.full(len(dirs), shape.volume))
    exact = _exact_slabs(shape, dirs, grid)
    assert np.abs(m.profiles.numpy() - exact).max() < 0.02 * shape.volume  # smoothing blurs a little
    raw, free = simulate_measurement(shape, dirs[:2], n_slabs=20, progress=False)  # no grid: bounding sphere
    assert free.n_slabs == 20 and float(free.offsets[0]) == pytest.approx(-shape.radius())
    assert raw.header.step_mm == 1.0


def test_noisy_measurement_reports_sigma_and_saves(tmp_path):
    shape, grid, dirs = SHAPES["ball"]
    raw, m = simulate_measurement(shape, dirs, grid=grid, sensor=LevelSensor(snr_db=30.0), seed=4, progress=False)
    assert m.sigma is not None and (m.sigma > 0).all()
    err = (m.profiles.numpy() - _exact_slabs(shape, dirs, grid))
    inside = _exact_slabs(shape, dirs, grid) > 0.2 * _exact_slabs(shape, dirs, grid).max()
    ratio = err[inside].std() / m.sigma.numpy()[inside].mean()
    assert 0.5 < ratio < 2.0
    again = simulate_measurement(shape, dirs, grid=grid, sensor=LevelSensor(snr_db=30.0), seed=4, progress=False)[1]
    assert torch.equal(again.profiles, m.profiles)
    m.save(tmp_path / "m.npz")
    assert torch.equal(DipMeasurement.load(tmp_path / "m.npz").profiles, m.profiles)
    back = read_rawscan(raw.save(tmp_path / "raw.jsonl"))
    assert back.header == raw.header
    np.testing.assert_array_equal(back.orientations[3].values, raw.orientations[3].values)


def test_dimension_mismatch():
    with pytest.raises(ValueError, match="3D but the grid is 2D"):
        simulate_measurement(SHAPES["ball"][0], DIRS3, grid=GRID2, progress=False)
    with pytest.raises(ValueError, match="directions must have shape"):
        simulate_measurement(SHAPES["ball"][0], DIRS2, grid=GRID3, progress=False)


def test_a_grid_that_is_no_grid_is_named():
    """Before: "AttributeError: 'int' object has no attribute 'ndim'"."""
    with pytest.raises(TypeError, match=r"grid must be a dipnet.Grid, e.g. Grid\(16, "):
        simulate_measurement(Ball(10.0), fibonacci_hemisphere(4), grid=16, progress=False)
