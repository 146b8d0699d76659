"""RigGeometry: apply / invert round trips, mismatched simulations, calibration files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.simulator.physics import LevelSensor, Tank
from dipnet.core.calibration_file import (Calibration, CalibrationFileError, load_calibration, save_calibration,
                                          scan_calibration)
from dipnet.preprocessing.recorded import read_scan
from dipnet.core.orientations import direction_to_rig
from dipnet.core.geometry import GeometryError, RigGeometry, invert_scan
from dipnet.shapes import Box
from dipnet.simulator.simulate import simulate_measurement

MISMATCH = RigGeometry(pivot_mm=20.0, tilt_axis_offset_mm=15.0, tilt_zero_deg=1.0, spin_zero_deg=-2.0,
                       step_scale=1.01, cross_section_mm2=0.92 * 60000.0, level_drift_mm_per_s=2e-4,
                       sensor_lag_s=0.7)
SHAPE = Box((22.0, 12.0, 30.0), (-4.0, 5.0, 3.0))
GRID = Grid(24, extent=100.0)
DIRS = fibonacci_hemisphere(12)


def test_levels_round_trip():
    time_s = np.concatenate([[0.0], 2.0 + 2.0 * np.arange(30)])
    levels = 150.0 + np.clip(np.linspace(-1, 3, 31), 0, None)
    slow = MISMATCH.with_values(sensor_lag_s=3.0)
    readings = slow.apply_levels(levels, time_s)
    assert np.abs(readings - levels).max() > 0.05  # the lag and drift are visible
    np.testing.assert_allclose(slow.invert_levels(readings, time_s), levels, atol=1e-9)


def test_height_model_is_the_issues_formula():
    tilts = np.array([0.0, 20.0, 35.0])
    r = np.radians(tilts + 1.0)
    expected = -40.0 + 20.0 * (np.cos(r) - 1.0) + 15.0 * np.sin(r)
    np.testing.assert_allclose(MISMATCH.start_heights(tilts, -40.0), expected)
    np.testing.assert_allclose(RigGeometry().start_heights(tilts, -40.0), -40.0)


def _profiles(geometry, reader, directions=DIRS):
    _, m = simulate_measurement(SHAPE, directions, grid=GRID, tank=Tank(60000.0),
                                sensor=LevelSensor(), geometry=geometry, reader_geometry=reader, progress=False)
    return m


def test_mismatch_is_measurable_and_the_true_geometry_undoes_it():
    ideal = _profiles(None, None)
    nominal = _profiles(MISMATCH, None)
    inverted = _profiles(MISMATCH, MISMATCH)
    true_directions = MISMATCH.directions(*direction_to_rig(DIRS))  # where the rig really dipped
    exact = _profiles(None, None, true_directions)
    scale = ideal.profiles.abs().max().item()
    assert (nominal.profiles - ideal.profiles).abs().max().item() > 0.2 * scale
    # the 8 % smaller tank inflates every volume by 1 / 0.92, the drift adds ~ 2e-4 mm/s x ~200 s x A
    volume = ideal.profiles.sum(1).mean().item()
    assert nominal.profiles.sum(1).mean().item() == pytest.approx(volume / 0.92 + 0.04 * 60000.0, rel=0.01)
    assert torch.allclose(inverted.directions, true_directions, atol=1e-12)
    assert (inverted.profiles - exact.profiles).abs().max().item() < 2e-3 * scale


def test_invert_refuses_what_it_cannot_apply():
    raw = read_scan(CATS_CSV)
    with pytest.raises(GeometryError, match="reading times"):
        invert_scan(raw, RigGeometry(level_drift_mm_per_s=1e-3))


def test_numbers_written_as_yaml_strings_are_read():
    # YAML 1.1 (PyYAML) reads 1e-4 and 2e1 (no dot) as strings
    geometry = RigGeometry.from_dict(yaml.safe_load("level_drift_mm_per_s: 1e-4\npivot_mm: 2e1\n"))
    assert geometry.level_drift_mm_per_s == 1e-4 and geometry.pivot_mm == 20.0
    with pytest.raises(GeometryError, match="pivot_mm must be a finite number, got 'abc'"):
        RigGeometry.from_dict({"pivot_mm": "abc"})


@pytest.mark.parametrize("values, cause", [
    ({"pivot": 3.0}, "unknown rig geometry key"),
    ({"cross_section_mm2": -5.0}, "cross_section_mm2 must be positive"),
    ({"cross_section_mm2": 0.0}, "cross_section_mm2 must be positive"),
    ({"step_scale": 1.6}, "step_scale=1.6 is unphysical"),
    ({"tilt_zero_deg": 60.0}, "tilt_zero_deg=60.0 exceeds"),
    ({"sensor_lag_s": -1.0}, r"sensor_lag_s must be in \[0, 600\] s"),
    ({"sensor_lag_s": 1e300}, r"sensor_lag_s must be in \[0, 600\] s"),
    ({"cross_section_mm2": 1e-300}, r"cross_section_mm2=1e-300 is outside \[1, 1e\+08\] mm\^2"),
    ({"cross_section_mm2": 1e300}, "cross_section_mm2=1e.300 is outside"),
    ({"level_drift_mm_per_s": -1e300}, "level_drift_mm_per_s=-1e.300 exceeds 1.0 mm/s"),
    ({"pivot_mm": float("nan")}, "pivot_mm must be a finite number"),
])
def test_unphysical_geometry_is_refused(values, cause):
    with pytest.raises(GeometryError, match=cause):
        RigGeometry.from_dict(values)


def _write(path, **changes):
    data = Calibration(MISMATCH, rig="rig-a", tank="tank-1", method="reference").to_dict()
    data.update(changes)
    path.write_text(json.dumps(data))
    return path


def test_calibration_file_round_trip(tmp_path):
    cal = Calibration(MISMATCH, rig="rig-a", tank="tank-1", method="self", uncertainty={"pivot_mm": 0.4})
    for name in ("cal.yaml", "cal.json"):
        back = load_calibration(save_calibration(cal, tmp_path / name), rig="rig-a", tank="tank-1")
        assert back.geometry == MISMATCH and back.uncertainty == {"pivot_mm": 0.4} and back.method == "self"


@pytest.mark.parametrize("changes, kwargs, cause", [
    ({"extra": 1}, {}, r"unknown key\(s\) \['extra'\]"),
    ({"format": "something"}, {}, "not a rig calibration"),
    ({"version": 7}, {}, "unsupported calibration version 7"),
    ({"rig": ""}, {}, "'rig' must name the rig"),
    ({"geometry": {"cross_section_mm2": -1.0}}, {}, "cross_section_mm2 must be positive"),
    ({"geometry": {"step_scale": 0.2}}, {}, "step_scale=0.2 is unphysical"),
    ({"geometry": {"pivott_mm": 1.0}}, {}, "unknown rig geometry key"),
    ({}, {"rig": "rig-b"}, "calibrated on rig 'rig-a', not on 'rig-b'"),
    ({}, {"tank": "tank-2"}, "calibrated on tank 'tank-1', not on 'tank-2'"),
])
def test_bad_calibration_files_name_the_cause(tmp_path, changes, kwargs, cause):
    path = _write(tmp_path / "cal.json", **changes)
    with pytest.raises(CalibrationFileError, match=cause) as info:
        load_calibration(path, **kwargs)
    assert str(path) in str(info.value)


def test_calibration_file_must_match_the_scan(tmp_path):
    raw, _ = simulate_measurement(SHAPE, fibonacci_hemisphere(3), grid=GRID, progress=False)
    path = _write(tmp_path / "cal.json")
    with pytest.raises(CalibrationFileError, match="not on 'dipnet.simulator'"):
        scan_calibration(path, raw.header)
    with pytest.raises(CalibrationFileError, match="calibration file not found"):
        load_calibration(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("format: [unclosed")
    with pytest.raises(CalibrationFileError, match="not a readable calibration file"):
        load_calibration(tmp_path / "bad.yaml")
