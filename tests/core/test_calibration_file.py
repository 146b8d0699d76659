"""Rig calibration files: round trips in YAML and JSON, and one clear refusal per bad file."""

import pytest

from dipnet.core.calibration_file import (TANK_CONFIG_KEY, Calibration, CalibrationFileError, load_calibration,
                                          save_calibration, scan_calibration)
from dipnet.core.geometry import RigGeometry
from dipnet.core.rawscan import ScanHeader

CAL = Calibration(RigGeometry(pivot_mm=20.1, tilt_axis_offset_mm=-3.0, cross_section_mm2=60000.0), rig="grbl-rig",
                  tank="tank-A", method="self", uncertainty={"pivot_mm": 0.3}, intervals={"pivot_mm": (19.6, 20.6)},
                  not_estimated={"spin_zero_deg": "a gauge of an unknown object"}, notes="test")


@pytest.mark.parametrize("name", ["cal.yaml", "cal.json"])
def test_a_calibration_round_trips(tmp_path, name):
    loaded = load_calibration(save_calibration(CAL, tmp_path / name), rig="grbl-rig", tank="tank-A")
    assert loaded == CAL


def test_another_rig_or_tank_is_refused_by_name(tmp_path):
    path = save_calibration(CAL, tmp_path / "cal.yaml")
    with pytest.raises(CalibrationFileError, match="calibrated on rig 'grbl-rig', not on 'marlin-rig'"):
        load_calibration(path, rig="marlin-rig")
    header = ScanHeader(quantity="level_mm", ndim=3, rig="grbl-rig", config={TANK_CONFIG_KEY: "tank-B"})
    with pytest.raises(CalibrationFileError, match="calibrated on tank 'tank-A', not on 'tank-B'"):
        scan_calibration(path, header)


@pytest.mark.parametrize("text,message", [
    ("[1, 2]", "expected a mapping"),
    ("format: other\n", "not a rig calibration"),
    ("format: dipnet.rig_calibration\nversion: 99\n", "unsupported calibration version"),
    ("bogus: 1\n", r"unknown key\(s\) \['bogus'\]"),
])
def test_malformed_files_get_one_message(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationFileError, match=message):
        load_calibration(path)


def test_an_unphysical_geometry_names_the_field(tmp_path):
    path = save_calibration(CAL, tmp_path / "cal.yaml")
    path.write_text(path.read_text().replace("step_scale: 1.0", "step_scale: 3.0"))
    with pytest.raises(CalibrationFileError, match="step_scale"):
        load_calibration(path)
    with pytest.raises(CalibrationFileError, match="not found"):
        load_calibration(tmp_path / "none.yaml")
