"""RawScan: in-memory construction, the append-only JSON Lines file, crash tolerance, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dipnet.core.orientations import rig_to_direction
from dipnet.core.rawscan import OrientationScan, RawScan, RawScanFileError, ScanHeader, read_rawscan
from dipnet.core.rawscan_writer import RawScanWriter


def _header(**changes) -> ScanHeader:
    base = dict(tank_cross_section_mm2=60000.0, step_mm=1.0, rig="test-rig", t_start_mm=-50.0,
                config={"sensor": "level"}, metadata={"object": "cup"})
    return ScanHeader(**{**base, **changes})


def _scan() -> RawScan:
    a = OrientationScan(k=0, direction=[0.0, 0.0, 1.0], meta={"noise_sigma": 0.02},
                        stage_mm=[0.0, 1.0, 2.0], values=[150.0, 150.1, 150.3], time_s=[2.0, 4.0, 6.0],
                        flags=[[], ["unstable"], []], complete=True)
    b = OrientationScan(k=1, tilt_deg=30.0, spin_deg=40.0, stage_mm=[0.0, 1.0], values=[150.0, 150.05],
                        time_s=[40.0, 42.0], complete=False)
    return RawScan(header=_header(), orientations=[a, b])


def _write_partial(path) -> None:
    """Orientation 0 complete, orientation 1 with two readings and a line cut mid-write."""
    with RawScanWriter(path, _header(), resume=False) as w:
        w.begin_orientation(0, tilt_deg=0.0, spin_deg=0.0)
        for i in range(3):
            w.append_reading(i * 1.0, 150.0 + 0.1 * i, 2.0 * i)
        w.complete_orientation()
        w.begin_orientation(1, tilt_deg=10.0, spin_deg=0.0)
        w.append_reading(0.0, 150.0, 10.0)
        w.append_reading(1.0, 150.2, 12.0)
    with open(path, "ab") as fh:
        fh.write(b'{"type": "reading", "k": 1, "stage_mm": 2.0, "val')


def test_file_round_trip(tmp_path):
    scan = _scan()
    scan.sessions = [{"first_k": 0, "controller": {"dialect": "grbl", "firmware": "1.1h"}}]
    path = scan.save(tmp_path / "scan.jsonl")
    back = read_rawscan(path)
    assert back.header == scan.header and back.sessions == scan.sessions
    assert back.header.units == {"stage": "mm", "value": "mm", "time": "s", "angles": "deg",
                                 "tank_cross_section": "mm^2"}
    assert len(back.orientations) == 2 and not back.truncated
    for a, b in zip(scan.orientations, back.orientations):
        np.testing.assert_array_equal(a.stage_mm, b.stage_mm)
        np.testing.assert_array_equal(a.values, b.values)
        np.testing.assert_array_equal(a.time_s, b.time_s)
        assert a.flags == b.flags and a.complete == b.complete and a.meta == b.meta
    assert back.complete_orientations() == [0]
    # every line is one JSON object with a type
    kinds = [json.loads(line)["type"] for line in path.read_text().splitlines()]
    assert kinds == ["header", "session", "orientation", "reading", "reading", "reading", "complete",
                     "orientation", "reading", "reading"]


def test_a_copy_without_the_stated_noise_keeps_everything_else():
    raw = _scan()
    raw.header = _header(noise_sigma=0.01)
    raw.orientations[1].meta = {"noise_sigma": 0.03, "t_start_mm": -40.0}
    quiet = raw.without_stated_noise()
    assert quiet.header.noise_sigma is None and [o.meta for o in quiet.orientations] == [{}, {"t_start_mm": -40.0}]
    assert raw.header.noise_sigma == 0.01 and raw.orientations[0].meta == {"noise_sigma": 0.02}  # the original kept
    for a, b in zip(raw.orientations, quiet.orientations):
        np.testing.assert_array_equal(a.values, b.values)
        assert (a.k, a.flags, a.complete) == (b.k, b.flags, b.complete)


def test_direction_from_rig_angles():
    scan = _scan()
    np.testing.assert_allclose(scan.orientations[1].unit_direction, rig_to_direction(30.0, 40.0)[0].numpy())
    np.testing.assert_allclose(scan.directions(complete_only=False)[0].numpy(), [0, 0, 1])
    assert scan.directions().shape == (1, 3)
    with pytest.raises(ValueError, match="direction or both"):
        OrientationScan(k=3, tilt_deg=10.0)


def test_truncated_last_line_is_tolerated_and_resume_info(tmp_path):
    path = tmp_path / "scan.jsonl"
    _write_partial(path)
    scan = read_rawscan(path)
    assert scan.truncated
    assert scan.complete_orientations() == [0]
    assert scan.next_orientation() == 1
    assert scan.orientations[1].n_readings == 2 and not scan.orientations[1].complete



@pytest.mark.parametrize("resume", [False, True])
def test_a_header_cut_short_says_the_file_holds_no_reading_and_to_delete_it(tmp_path, resume):
    """A scan that stopped as it began (power lost while its header was written): the file holds a part of its header
    only. Before: ``scan.jsonl:1: not valid JSON (Unterminated string starting at)``, for a read and for the
    resume alike, saying neither that nothing was recorded nor what to do."""
    path = tmp_path / "scan.jsonl"
    path.write_text(json.dumps(_header().to_json())[:60])
    with pytest.raises(RawScanFileError, match=r"scan\.jsonl:1: its only line is not valid JSON \(.+\): "
                                               r"a raw scan header cut short .* holds no reading; "
                                               r"delete the file to scan afresh"):
        if resume:
            RawScanWriter(path, _header(), resume=True)
        else:
            read_rawscan(path)

def test_resume_restarts_the_incomplete_orientation(tmp_path):
    path = tmp_path / "scan.jsonl"
    _write_partial(path)
    with RawScanWriter(path, _header(), resume=True) as w:
        assert w.scan.next_orientation() == 1
        w.begin_orientation(1, tilt_deg=10.0, spin_deg=0.0)
        for i in range(4):
            w.append_reading(i * 1.0, 151.0 + i, 100.0 + i)
        w.complete_orientation()
        with pytest.raises(ValueError, match="already complete"):
            w.begin_orientation(0, tilt_deg=0.0, spin_deg=0.0)
    for line in path.read_text().splitlines():  # the cut line is gone, nothing is glued to it
        json.loads(line)
    scan = read_rawscan(path)
    assert not scan.truncated and scan.complete_orientations() == [0, 1]
    np.testing.assert_array_equal(scan.orientations[1].values, [151.0, 152.0, 153.0, 154.0])


def test_resume_after_unterminated_complete_line(tmp_path):
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, _header(), resume=False) as w:
        w.begin_orientation(0, direction=[0, 0, 1])
        w.append_reading(0.0, 150.0, 0.0)
    path.write_bytes(path.read_bytes().rstrip(b"\n"))
    with RawScanWriter(path, _header(), resume=True) as w:
        assert w.scan.orientations[0].n_readings == 1  # the unterminated reading was kept
        w.begin_orientation(0, direction=[0, 0, 1])
        w.append_reading(0.0, 150.5, 1.0)
        w.complete_orientation()
    scan = read_rawscan(path)
    assert scan.complete_orientations() == [0] and scan.orientations[0].values.tolist() == [150.5]


def test_writer_refuses_incompatible_or_existing_files(tmp_path):
    path = tmp_path / "scan.jsonl"
    _write_partial(path)
    with pytest.raises(RawScanFileError, match="cannot resume"):
        RawScanWriter(path, _header(step_mm=2.0), resume=True)
    with pytest.raises(FileExistsError):
        RawScanWriter(path, _header(), resume=False)
    with RawScanWriter(tmp_path / "new.jsonl", _header(), resume=True) as w:  # resume on a new file
        with pytest.raises(RuntimeError, match="begin_orientation"):
            w.append_reading(0.0, 1.0, 0.0)


@pytest.mark.parametrize("lines, line_no, message", [
    (["HEADER", '{"type": "reading", "k": 0, "stage_mm": 0, "value": 1, "time_s": 0}'], 2, "never begun"),
    (["HEADER", "not json", '{"type": "orientation", "k": 0, "direction": [0, 0, 1]}'], 2, "not valid JSON"),
    (["HEADER", '{"type": "orientation", "k": 0, "direction": [0, 0, 1]}',
      '{"type": "reading", "k": 0, "value": 1, "time_s": 0}'], 3, "missing field 'stage_mm'"),
    (["HEADER", '{"type": "orientation", "k": 0, "direction": [0, 1]}'], 2, "3 components"),
    (["HEADER", '{"type": "pause"}'], 2, "unknown record type"),
    (['{"type": "orientation", "k": 0}'], 1, "first line must be the header"),
    (['{"type": "header", "format": "other"}'], 1, "not a dipnet raw scan"),
    (["HEADER", '{"type": "orientation", "k": 0, "direction": [0, 0, 1]}',
      '{"type": "complete", "k": 0, "n_readings": 5}'], 3, "marked complete with 5"),
])
def test_malformed_file_names_file_and_line(tmp_path, lines, line_no, message):
    path = tmp_path / "bad.jsonl"
    header = json.dumps(_header().to_json())
    path.write_text("\n".join(header if x == "HEADER" else x for x in lines) + "\n")
    with pytest.raises(RawScanFileError, match=message) as info:
        read_rawscan(path)
    assert f"{path}:{line_no}:" in str(info.value)


def _orientation_line(k: int, direction, tilt_deg: float, spin_deg: float) -> str:
    return json.dumps({"type": "orientation", "k": k, "direction": list(direction), "tilt_deg": tilt_deg,
                       "spin_deg": spin_deg})


def test_a_direction_that_contradicts_its_rig_angles_is_refused(tmp_path):
    """A record holding both a direction and rig angles is dipped along the angles (invert_scan):
    angles that mean another direction (an elevation for a tilt: a torus at 20^3 then came back at
    IoU 0.10 against its true reconstruction, "consistent") are refused, naming the line."""
    header = json.dumps(_header().to_json())
    true = rig_to_direction(20.0, 30.0)[0].numpy()
    path = tmp_path / "ok.jsonl"  # a direction rounded to 3 decimals (0.03 deg) agrees with its angles
    path.write_text("\n".join([header, _orientation_line(0, np.round(true, 3).tolist(), 20.0, 30.0)]) + "\n")
    assert read_rawscan(path).orientations[0].tilt_deg == 20.0
    path = tmp_path / "elevation.jsonl"
    path.write_text("\n".join([header, _orientation_line(0, true.tolist(), 20.0, 30.0),
                               _orientation_line(1, true.tolist(), 70.0, 30.0)]) + "\n")
    with pytest.raises(RawScanFileError, match=r"orientation 1: its direction .* is 50.0 deg from the one its "
                                                r"rig angles give \(tilt 70 deg, spin 30 deg") as info:
        read_rawscan(path)
    assert f"{path}:3:" in str(info.value)
    path = tmp_path / "zero.jsonl"
    path.write_text("\n".join([header, _orientation_line(0, [0.0, 0.0, 0.0], 20.0, 30.0)]) + "\n")
    with pytest.raises(RawScanFileError, match=r"zero.jsonl:2: orientation 0: direction \[0.0, 0.0, 0.0\] is not a "
                                                r"direction"):
        read_rawscan(path)


def test_missing_and_empty_files(tmp_path):
    with pytest.raises(RawScanFileError, match="not found"):
        read_rawscan(tmp_path / "nope.jsonl")
    (tmp_path / "empty.jsonl").write_text("\n")
    with pytest.raises(RawScanFileError, match="empty"):
        read_rawscan(tmp_path / "empty.jsonl")


def test_header_validation():
    with pytest.raises(ValueError, match="quantity"):
        ScanHeader(quantity="volts")
    with pytest.raises(ValueError, match="tank_cross_section_mm2"):
        ScanHeader(tank_cross_section_mm2=-1.0)
    assert ScanHeader(quantity="mass_g", ndim=2).units["value"] == "g"
    assert ScanHeader(ndim=2).units["tank_cross_section"] == "mm"


def test_a_header_whose_ndim_was_edited_names_the_dimension_behind_its_section_unit(tmp_path):
    """Before: a 3D scan's header edited to ``ndim: 2`` said only "units.tank_cross_section: unknown unit 'mm^2'"."""
    header = {**_header().to_json(), "ndim": 2}
    path = tmp_path / "edited.jsonl"
    path.write_text(json.dumps(header) + "\n")
    with pytest.raises(RawScanFileError, match=r"edited.jsonl:1: units.tank_cross_section: unknown unit 'mm\^2'; .* "
                                                r"\('mm\^2' is the unit of a 3D tank's section: is the header's ndim=2 "
                                                r"right\?\)"):
        read_rawscan(path)
    with pytest.raises(ValueError, match=r"'mm' is the unit of a 2D tank's section: is the header's ndim=3 right"):
        _header().unit_factors({"tank_cross_section": "mm"})
    with pytest.raises(ValueError) as info:  # no hint for a unit of neither kind
        _header().unit_factors({"tank_cross_section": "litre"})
    assert "ndim" not in str(info.value)


def test_a_scan_resumed_in_another_tank_is_refused_naming_the_tanks(tmp_path):
    """The tank a scan records (``+rig.tank``) is what its calibration file is checked against, so a resumed
    scan cannot change it; a scan that records no tank can be resumed with one."""
    path = tmp_path / "scan.jsonl"
    header = ScanHeader(quantity="level_mm", step_mm=2.0, config={"tank_id": "lab-tank-1"})
    RawScanWriter(path, header, fsync=False).close()
    other = ScanHeader(quantity="level_mm", step_mm=2.0, config={"tank_id": "lab-tank-2"})
    with pytest.raises(RawScanFileError, match=r"rig.tank \(config.tank_id\) 'lab-tank-1' -> 'lab-tank-2'"):
        RawScanWriter(path, other, fsync=False)
    untold = ScanHeader(quantity="level_mm", step_mm=2.0, config={})
    assert header.differences(untold) == [] and untold.differences(header) == []


def test_reading_times_that_run_backwards_within_a_dip_are_named(tmp_path):
    """The audit's case: a ``.jsonl`` whose ``time_s`` ran backwards within a dip was read without a word
    (a drift or sensor lag fitted against those times is wrong). Kept with a warning naming the file and line,
    since the runner's wall-clock times can be set back while the readings are sound."""
    path = tmp_path / "clock.jsonl"
    reading = '{{"type": "reading", "k": {k}, "stage_mm": {s}, "value": 1, "time_s": {t}}}'
    lines = [json.dumps(_header().to_json()),
             '{"type": "orientation", "k": 0, "direction": [0, 0, 1]}',
             *(reading.format(k=0, s=s, t=t) for s, t in ((0, 10.0), (1, 11.0), (2, 10.5), (3, 12.0))),
             '{"type": "complete", "k": 0}',
             '{"type": "orientation", "k": 1, "direction": [0, 0, 1]}',  # a new dip may start earlier: no word
             *(reading.format(k=1, s=s, t=t) for s, t in ((0, 1.0), (1, 2.0), (2, 2.0)))]
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(UserWarning) as caught:
        raw = read_rawscan(path)
    assert [str(w.message) for w in caught] == [
        f"{path}:5: orientation 0: time 10.5 s after 11 s: the reading times run backwards within the dip (a clock "
        "set back, or readings edited?); the readings are kept, but a level drift or sensor lag fitted against "
        "these times is wrong: fix the times, or do not fit level_drift_mm_per_s or sensor_lag_s from this recording"]
    assert raw.orientations[0].n_readings == 4
    lines[5] = reading.format(k=0, s=3, t=9.0)  # and the second dip's last reading 1 s early
    path.write_text("\n".join(lines[:-1] + [reading.format(k=1, s=2, t=1.0)]) + "\n")
    with pytest.warns(UserWarning, match=r":5: orientation 0: time 10.5 s after 11 s: .* within the dip \(3 "
                                         r"backward steps in 2 dip\(s\): 0, 1\)"):
        read_rawscan(path)


def test_a_negative_reading_quantum_or_noise_is_refused_naming_it():
    """Before: ``scan.py rig.resolution=-1`` recorded ``"resolution": -1`` and reconstruct.py read it back as the
    sensor's quantum (``quantum_volume_mm3: -20000`` in metrics.json)."""
    with pytest.raises(ValueError, match=r"^resolution \(the readings' quantum, in their unit; scan.py: "
                                         r"rig.resolution\) must be a number >= 0 or null, got -1$"):
        ScanHeader(quantity="level_mm", step_mm=2.0, resolution=-1)
    with pytest.raises(ValueError, match=r"^noise_sigma \(the readings' noise, in their unit\) must be .*got nan$"):
        ScanHeader(quantity="level_mm", step_mm=2.0, noise_sigma=float("nan"))
    assert ScanHeader(quantity="level_mm", step_mm=2.0, resolution=0.0, noise_sigma=None).resolution == 0.0


@pytest.mark.parametrize("header, orientation, message", [
    ({"t_start_mm": "abc"}, {}, r":1: t_start_mm \(the water line's height at stage 0, mm\) must be a finite number "
                                r"or null, got 'abc'"),
    ({"t_start_mm": [1, 2]}, {}, r":1: t_start_mm .* got \[1, 2\]"),
    ({"config": [1]}, {}, r":1: config must be a JSON object"),
    ({"metadata": "cup"}, {}, r":1: metadata must be a JSON object"),
    ({}, {"meta": [1]}, r":2: orientation 0: meta must be a JSON object"),
    ({}, {"meta": {"t_start_mm": "x"}}, r":2: orientation 0: meta.t_start_mm .* got 'x'"),
    ({}, {"meta": {"noise_sigma": -5.0}}, r":2: orientation 0: meta.noise_sigma .* must be a number >= 0 or null, "
                                          r"got -5.0"),
    ({}, {"meta": {"noise_sigma": "x"}}, r":2: orientation 0: meta.noise_sigma"),
])
def test_header_and_orientation_fields_of_the_wrong_type_name_file_and_line(tmp_path, header, orientation, message):
    """Before: a traceback once preprocessing used them (``TypeError: can only concatenate str``, ``AttributeError:
    'list' object has no attribute 'get'``), and an orientation's negative ``noise_sigma`` was read as its
    magnitude (the header's is refused)."""
    path = tmp_path / "bad.jsonl"
    lines = [{**_header().to_json(), **header},
             {"type": "orientation", "k": 0, "direction": [0, 0, 1], **orientation},
             {"type": "reading", "k": 0, "stage_mm": 0.0, "value": 150.0, "time_s": 2.0}]
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    with pytest.raises(RawScanFileError, match=message):
        read_rawscan(path)


@pytest.mark.parametrize("orientation, reading, line_no, message", [
    ({"k": 0.5}, {}, 2, r"orientation index k must be a whole number, got 0.5"),
    ({}, {"k": 2.5}, 3, r"orientation index k must be a whole number, got 2.5"),
    ({"k": True}, {}, 2, r"orientation index k must be a whole number, got True"),
    ({}, {"stage_mm": "0"}, 3, r"stage_mm must be a number, got '0'"),
    ({}, {"value": "150.0"}, 3, r"value must be a number, got '150.0'"),
    ({}, {"time_s": True}, 3, r"time_s must be a number, got True"),
])
def test_an_index_or_reading_of_the_wrong_type_names_file_and_line(tmp_path, orientation, reading, line_no, message):
    """Before: ``k: 0.5`` was read as orientation 0 and ``"stage_mm": "0"`` (a string) as 0 mm, without a word."""
    path = tmp_path / "bad.jsonl"
    lines = [_header().to_json(), {"type": "orientation", "k": 0, "direction": [0, 0, 1], **orientation},
             {"type": "reading", "k": 0, "stage_mm": 0.0, "value": 150.0, "time_s": 2.0, **reading}]
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    with pytest.raises(RawScanFileError, match=f"^{path}:{line_no}: {message}$"):
        read_rawscan(path)
    whole = [lines[0], {"type": "orientation", "k": 1.0, "direction": [0, 0, 1]},
             {"type": "reading", "k": "1", "stage_mm": 0, "value": 150, "time_s": 2.0}]
    path.write_text("".join(json.dumps(line) + "\n" for line in whole))
    read = read_rawscan(path).orientations[0]  # 1.0 and "1" (a string index) are still orientation 1
    assert read.k == 1 and read.stage_mm.tolist() == [0.0] and read.values.tolist() == [150.0]


@pytest.mark.parametrize("orientation, complete, line_no, message", [
    ({"tilt_deg": "10", "spin_deg": 0.0}, {}, 2, r"tilt_deg must be a number, got '10'"),
    ({"tilt_deg": 0.0, "spin_deg": True}, {}, 2, r"spin_deg must be a number, got True"),
    ({"tilt_deg": float("nan"), "spin_deg": 0.0}, {}, 2, r"tilt_deg must be a finite number, got nan"),
    ({"tilt_deg": 0.0, "spin_deg": float("inf")}, {}, 2, r"spin_deg must be a finite number, got inf"),
    ({"direction": ["0", 0, 1]}, {}, 2, r"direction must be a list of numbers, got \['0', 0, 1\]"),
    ({"direction": [False, False, True]}, {}, 2, r"direction must be a list of numbers, got \[False, False, True\]"),
    ({}, {"n_readings": "1"}, 4, r"n_readings must be a whole number, got '1'"),
    ({}, {"n_readings": True}, 4, r"n_readings must be a whole number, got True"),
    ({}, {"n_readings": 1.5}, 4, r"n_readings must be a whole number, got 1.5"),
])
def test_rig_angles_or_a_reading_count_of_the_wrong_type_name_file_and_line(tmp_path, orientation, complete, line_no,
                                                                          message):
    """Before: ``"tilt_deg": "10"`` (a string) was read as 10 degrees, ``"n_readings": true`` as 1 reading and
    ``1.5`` as 1, a NaN or infinite angle gave a NaN direction and ``"direction": ["0", 0, 1]`` was read as
    numbers, without a word."""
    path = tmp_path / "bad.jsonl"
    lines = [_header().to_json(), {"type": "orientation", "k": 0, "direction": None, "tilt_deg": 0.0,
                                   "spin_deg": 0.0, **orientation},
             {"type": "reading", "k": 0, "stage_mm": 0.0, "value": 150.0, "time_s": 2.0},
             {"type": "complete", "k": 0, "n_readings": 1, **complete}]
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    with pytest.raises(RawScanFileError, match=f"^{path}:{line_no}: {message}$"):
        read_rawscan(path)
    lines[1].update(direction=None, tilt_deg=10, spin_deg=0)
    lines[3].update(n_readings=1.0)
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    read = read_rawscan(path).orientations[0]  # whole numbers (and 1.0 readings) still read
    assert read.tilt_deg == 10.0 and read.complete


@pytest.mark.parametrize(("line_no", "old", "new"), [
    (1, '"tank_cross_section_mm2": 60000.0', '"tank_cross_section_mm2": 60000.0, "tank_cross_section_mm2": 3e4'),
    (3, '"value": 150.0', '"value": 150.0, "value": 160.0')])
def test_a_key_given_twice_names_file_line_and_key(tmp_path, line_no, old, new):
    """``json.loads`` keeps the last of two equal keys: a header edited to hold the tank section twice read the
    second (every volume halved, exit 0, no warning)."""
    path = _scan().save(tmp_path / "scan.jsonl")
    lines = path.read_text().splitlines()
    assert old in lines[line_no - 1]
    lines[line_no - 1] = lines[line_no - 1].replace(old, new, 1)
    path.write_text("\n".join(lines) + "\n")
    key = old.split('"')[1]
    with pytest.raises(RawScanFileError, match=rf"scan\.jsonl:{line_no}: key '{key}' is given twice"):
        read_rawscan(path)


def test_a_header_step_that_contradicts_the_stage_readings_is_warned_naming_both(tmp_path, recwarn):
    path = _scan().save(tmp_path / "ok.jsonl")  # readings 1 mm apart, as the header says: no word
    read_rawscan(path)
    assert not [w for w in recwarn if "step_mm" in str(w.message)]
    scan = _scan()
    for o in scan.orientations:  # stage readings in cm: 0.1 mm steps against the header's 1 mm
        o.stage_mm = o.stage_mm / 10
    path = scan.save(tmp_path / "cm.jsonl")
    with pytest.warns(UserWarning, match=r"cm\.jsonl: the header's step_mm=1 mm, .*stage steps are 0\.1 mm"):
        read = read_rawscan(path)
    np.testing.assert_array_equal(read.orientations[0].stage_mm, [0.0, 0.1, 0.2])  # results unchanged
