"""Rig calibration files: round trips in YAML and JSON, and one clear refusal per bad file."""

import math
import os
import re
import time

import pytest

from dipnet.core.calibration_file import (TANK_CONFIG_KEY, Calibration, CalibrationFileError, keep_previous,
                                          load_calibration, save_calibration, scan_calibration, scan_tank)
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


@pytest.mark.parametrize("interval", [(20.6, 19.6), (21.0, 22.0)])
def test_an_interval_that_cannot_hold_its_estimate_is_refused(tmp_path, interval):
    """The audit's case: a hand-edited file with its pivot's interval reversed, or beside its estimate, was read
    without a word (the intervals are what the file claims about its own accuracy)."""
    from dataclasses import replace

    path = save_calibration(replace(CAL, intervals={"pivot_mm": interval}), tmp_path / "cal.yaml")
    with pytest.raises(CalibrationFileError, match=rf"intervals_90.pivot_mm: \[{interval[0]:g}, {interval[1]:g}\] "
                                                   r"does not hold the estimate geometry.pivot_mm=20.1"):
        load_calibration(path)


def test_a_truncated_file_is_refused_naming_the_missing_keys(tmp_path):
    """The audit's case: a file cut after ``pivot_mm`` was read with ideal values for the rest (exit 0, a
    volume 5 % off). A version 2 file names every section and geometry field, so the cut one is refused."""
    path = save_calibration(CAL, tmp_path / "cal.yaml")
    text = path.read_text()
    path.write_text(text[:text.index("pivot_mm:") + len("pivot_mm: 20")])
    with pytest.raises(CalibrationFileError, match=r"cal.yaml: missing key\(s\) \['intervals_90', 'not_estimated', "
                                                   r"'notes', 'uncertainty', 'geometry.level_drift_mm_per_s'"
                                                   r".*truncated"):
        load_calibration(path)
    path.write_text(text.replace("  sensor_lag_s: 0.0\n", ""))
    with pytest.raises(CalibrationFileError, match=r"missing key\(s\) \['geometry.sensor_lag_s'\]"):
        load_calibration(path)



@pytest.mark.parametrize("name", ["cal.yaml", "cal.json"])
def test_a_save_killed_mid_write_leaves_the_previous_file_whole(tmp_path, monkeypatch, name):
    """A run killed while it wrote the file (simulated: the write stops halfway with ``KeyboardInterrupt``). Before:
    the file was written in place, so it was left cut short; a YAML file cut in its last section was read without a
    word (its fitted ball centre ``reference_centroid_mm: [24.9, 0.0, 0.0]`` for ``0.05123``, or none; its notes
    cut). Now it is written to a temporary file and renamed: the previous file stays whole, and no temporary is left."""
    import builtins
    import io
    from dataclasses import replace

    path = save_calibration(CAL, tmp_path / name)
    real_open = builtins.open

    class Killed:
        def __init__(self, stream):
            self.stream = stream

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.stream.close()

        def write(self, text):
            self.stream.write(text[:len(text) // 2])
            self.stream.flush()
            raise KeyboardInterrupt

    def open_killed(file, mode="r", *args, **kwargs):
        stream = real_open(file, mode, *args, **kwargs)
        return Killed(stream) if "w" in mode and str(tmp_path) in os.fspath(file) else stream

    monkeypatch.setattr(builtins, "open", open_killed)
    monkeypatch.setattr(io, "open", open_killed)
    with pytest.raises(KeyboardInterrupt):
        save_calibration(replace(CAL, notes="a new calibration", reference_centroid_mm=(24.9, 0.0, 0.05123)), path)
    monkeypatch.undo()
    assert load_calibration(path) == CAL
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]

@pytest.mark.parametrize("name", ["cal.yaml", "cal.json"])
def test_a_reference_calibrations_fitted_ball_centre_round_trips(tmp_path, name):
    """A reference ball off the spin axis records where it was fitted to be; a file without it (self-calibration,
    a centred ball) is complete, one with a malformed centre is refused naming the key."""
    fitted = Calibration(CAL.geometry, rig="grbl-rig", tank="tank-A", method="reference",
                         reference_centroid_mm=(24.9, 0.0, 0.05))
    path = save_calibration(fitted, tmp_path / name)
    assert "reference_centroid_mm" in path.read_text() and load_calibration(path) == fitted
    assert "reference_centroid_mm" not in save_calibration(CAL, tmp_path / name).read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(save_calibration(fitted, bad).read_text().replace("- 0.05\n", ""))
    with pytest.raises(CalibrationFileError, match=r"reference_centroid_mm must be \[x, y, z\] \(mm\)"):
        load_calibration(bad)


def test_a_nominal_section_and_version_1_omissions_are_read(tmp_path):
    nominal = Calibration(RigGeometry(pivot_mm=2.0), rig="grbl-rig", tank="tank-A")
    assert load_calibration(save_calibration(nominal, tmp_path / "nominal.yaml")) == nominal
    path = tmp_path / "v1.yaml"
    path.write_text("format: dipnet.rig_calibration\nversion: 1\nrig: r\ntank: t\ngeometry: {pivot_mm: 2.0}\n")
    assert load_calibration(path).geometry == RigGeometry(pivot_mm=2.0)


def test_the_scans_tank_is_its_header_tank_or_its_scan_configs():
    """Scans recorded before ``scan.py`` wrote ``tank_id`` keep ``+rig.tank`` in the scan config only."""
    def header(**config):
        return ScanHeader(quantity="level_mm", ndim=3, rig="r", config=config)

    assert scan_tank(header(**{TANK_CONFIG_KEY: "tank-B"})) == "tank-B"
    assert scan_tank(header(scan={"rig": {"tank": "tank-C"}})) == "tank-C"
    assert scan_tank(header(scan={"rig": {}})) is None and scan_tank(header()) is None


def test_an_unidentified_field_is_written_as_strict_json_and_read_as_unknown(tmp_path):
    cal = Calibration(CAL.geometry, rig="grbl-rig", tank="tank-A", method="self",
                      uncertainty={"pivot_mm": float("inf")}, intervals={"pivot_mm": (float("-inf"), float("inf"))})
    path = save_calibration(cal, tmp_path / "cal.json")
    assert "Infinity" not in path.read_text()
    loaded = load_calibration(path)
    assert math.isnan(loaded.uncertainty["pivot_mm"]) and all(math.isnan(v) for v in loaded.intervals["pivot_mm"])


def test_keep_previous_renames_an_earlier_file_by_its_time_and_never_over_another(tmp_path):
    path = tmp_path / "cal.yaml"
    assert keep_previous(path) is None  # nothing there: nothing to keep
    kept = []
    for text in ("first", "second"):
        save_calibration(CAL, path).write_text(text)
        os.utime(path, (1764531612, 1764531612))  # the same modification time both times
        kept.append(keep_previous(path))
    assert not path.exists() and [p.read_text() for p in kept] == ["first", "second"]
    stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(1764531612))
    assert [p.name for p in kept] == [f"cal.{stamp}.yaml", f"cal.{stamp}-1.yaml"]


@pytest.mark.parametrize("name,line", [("cal.yaml", r"\g<0>\n\1pivot_mm: 0.0"),
                                       ("cal.json", r'\g<0>\n\1"pivot_mm": 0.0,')])
def test_a_key_given_twice_is_refused_naming_it(tmp_path, name, line):
    """YAML and JSON readers keep the last of two equal keys: a hand-edit adding ``pivot_mm: 0.0`` below the
    calibrated pivot read the authors' cats with a pivot of 0 mm, exit 0 and ``consistent``."""
    path = save_calibration(CAL, tmp_path / name)
    text = path.read_text()
    path.write_text(re.sub(r'(?m)^( +)"?pivot_mm"?: .*$', line, text, count=1))
    with pytest.raises(CalibrationFileError, match=rf"{name}: .*key 'pivot_mm' is given twice"):
        load_calibration(path)
    path.write_text(text)
    assert load_calibration(path).geometry == CAL.geometry


@pytest.mark.parametrize("section, value, message", [
    ("uncertainty", {"pivot": 0.3}, r"unknown rig geometry key\(s\) \['pivot'\] in 'uncertainty'"),
    ("intervals_90", {"pivot": [19.0, 21.0]}, r"unknown rig geometry key\(s\) \['pivot'\] in 'intervals_90'"),
    ("not_estimated", {"spin_zero": "x"}, r"unknown rig geometry key\(s\) \['spin_zero'\] in 'not_estimated'"),
    ("uncertainty", {"pivot_mm": -0.3}, r"uncertainty.pivot_mm=-0.3: a standard error is >= 0"),
    ("uncertainty", [0.3], r"'uncertainty' must be a mapping of rig geometry fields, got list"),
    ("intervals_90", {"pivot_mm": 20.1}, r"intervals_90.pivot_mm must be \[low, high\]"),
    ("intervals_90", {"pivot_mm": [19.0, 20.1, 21.0]}, r"intervals_90.pivot_mm must be \[low, high\]"),
    ("reference_centroid_mm", [True, 0.0, 0.0], r"expected a number or null, got True"),  # was x = 1 mm
    ("version", True, r"unsupported calibration version True"),  # was version 1: its missing keys unchecked
])
def test_a_hand_edited_section_is_refused_naming_its_key(tmp_path, section, value, message):
    """Before: a typo's key was kept unread (its interval never checked against the estimate), a negative standard
    error or a third interval bound read without a word, and a list or a number in place of a mapping or a pair gave
    "'list' object has no attribute 'items'" / "'float' object is not subscriptable", naming no key."""
    import yaml

    path = save_calibration(CAL, tmp_path / "cal.yaml")
    data = yaml.safe_load(path.read_text())
    data[section] = value
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CalibrationFileError, match=r"cal.yaml: " + message):
        load_calibration(path)
