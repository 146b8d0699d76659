"""The raw scan writer: what it writes reads back, a resumed file goes on, a second writer is refused."""

import re

import numpy as np
import pytest

from dipnet.core.rawscan import RawScanFileError, ScanHeader, read_rawscan
from dipnet.core.rawscan_writer import RawScanLocked, RawScanWriter

HEADER = ScanHeader(quantity="level_mm", ndim=3, tank_cross_section_mm2=6e4, step_mm=1.0)


def _dip(writer, k, n=5):
    writer.begin_orientation(k, tilt_deg=10.0 * k, spin_deg=0.0)
    for i in range(n):
        writer.append_reading(float(i), 100.0 + 0.1 * i * i, float(i), flags=["unstable"] if i == 2 else [])
    writer.complete_orientation()


def test_written_readings_read_back_exactly(tmp_path):
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, HEADER, fsync=False) as w:
        _dip(w, 0)
        _dip(w, 1)
    scan = read_rawscan(path)
    assert [o.k for o in scan.completed()] == [0, 1] and scan.orientations[1].tilt_deg == 10.0
    o = scan.orientations[0]
    assert np.array_equal(o.stage_mm, np.arange(5.0)) and np.allclose(o.values, 100.0 + 0.1 * np.arange(5.0) ** 2)
    assert list(o.flags[2]) == ["unstable"] and list(o.flags[0]) == []


def test_a_resumed_scan_continues_after_the_last_complete_dip(tmp_path):
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, HEADER, fsync=False) as w:
        _dip(w, 0)
        w.begin_orientation(1, tilt_deg=10.0, spin_deg=0.0)
        w.append_reading(0.0, 100.0, 0.0)  # interrupted mid-dip
    with RawScanWriter(path, HEADER, fsync=False) as w:
        assert w.scan.next_orientation() == 1
        _dip(w, 1)
    assert [o.k for o in read_rawscan(path).completed()] == [0, 1]


def test_a_second_writer_and_other_settings_are_refused(tmp_path):
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, HEADER, fsync=False) as w:
        _dip(w, 0)
        with pytest.raises(RawScanLocked):
            RawScanWriter(path, HEADER, fsync=False)
    with pytest.raises(FileExistsError, match="resume=True"):
        RawScanWriter(path, HEADER, resume=False, fsync=False)
    other = ScanHeader(quantity="level_mm", ndim=3, tank_cross_section_mm2=5e4, step_mm=1.0)
    with pytest.raises(RawScanFileError, match="cannot resume"):
        RawScanWriter(path, other, fsync=False)


def _rig_header(**plan) -> ScanHeader:
    """A header as a rig run writes it: the plan, the geometry and the controller in ``config``."""
    settings = {"start_mm": 0.0, "stop_mm": 110.0, "step_mm": 1.0, "settle_s": 0.0, "origin_height_mm": 50.0, **plan}
    geometry = {"pivot_mm": plan.pop("pivot_mm", 0.0), "tilt_zero_deg": 0.0, "cross_section_mm2": None}
    axes = {"lower": {"letter": "Z", "scale": 1.0, "sign": -1, "offset": 0.0}}
    config = {"plan": {k: v for k, v in settings.items() if k != "pivot_mm"}, "rig_geometry": geometry,
              "controller": {"dialect": "grbl", "url": "/dev/ttyUSB0", "axes": axes},
              "sensor": {"kind": "LineSensor", "quantity": "level_mm", "pattern": "old", "slave": 1, "address": 0}}
    return ScanHeader(quantity="level_mm", ndim=3, tank_cross_section_mm2=6e4, step_mm=1.0, config=config)


def test_a_resume_with_other_dip_settings_is_refused_naming_them(tmp_path):
    """Before: another stop, origin height or rig geometry was appended to the recorded dips."""
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, _rig_header(), fsync=False) as w:
        _dip(w, 0)
    with pytest.raises(RawScanFileError) as refused:
        RawScanWriter(path, _rig_header(stop_mm=60.0, origin_height_mm=40.0, pivot_mm=5.0), fsync=False)
    message = str(refused.value)
    assert "cannot resume" in message and "(recorded -> new)" in message
    for named in ("protocol.stop_mm (config.plan.stop_mm) 110.0 -> 60.0",
                  "rig.origin_height_mm (config.plan.origin_height_mm) 50.0 -> 40.0",
                  "rig.geometry.pivot_mm (config.rig_geometry.pivot_mm) 0.0 -> 5.0"):
        assert named in message
    assert "settle" not in message and "pattern" not in message


@pytest.mark.parametrize("key,value,named", [
    ("start_mm", 5.0, "protocol.start_mm"),
    ("axes", {"lower": {"letter": "Z", "scale": 2.0, "sign": -1, "offset": 0.0}}, "rig.controller.axes.lower.scale"),
    ("kind", "ModbusLevelSensor", "sensor (config.sensor.kind)"),
    ("address", 2, "sensor.device.address (config.sensor.address) 0 -> 2"),  # before: a Modbus scan resumed reading
    ("slave", 3, "sensor.device.slave (config.sensor.slave) 1 -> 3"),        # another register or device, no word
])
def test_each_dip_setting_is_compared(tmp_path, key, value, named):
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, _rig_header(), fsync=False) as w:
        _dip(w, 0)
    changed = _rig_header()
    node = {"start_mm": "plan", "axes": "controller"}.get(key, "sensor")
    changed.config[node][key] = value
    with pytest.raises(RawScanFileError, match=re.escape(named)):
        RawScanWriter(path, changed, fsync=False)


def test_a_resume_with_the_same_dip_settings_goes_on(tmp_path):
    """Timing, the port and the sensor's line pattern may change; a header without the settings is not compared."""
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, _rig_header(), fsync=False) as w:
        _dip(w, 0)
    again = _rig_header(settle_s=0.5)
    again.config["controller"]["url"] = "/dev/ttyUSB1"
    again.config["sensor"]["pattern"] = "new"
    with RawScanWriter(path, again, fsync=False) as w:
        _dip(w, 1)
    with RawScanWriter(path, HEADER, fsync=False) as w:  # records no plan: nothing to compare
        assert w.scan.next_orientation() == 2
    assert [o.k for o in read_rawscan(path).completed()] == [0, 1]


def test_a_fake_rig_scan_resumed_with_another_object_is_refused_naming_it(tmp_path):
    """Before: ``scan.py rig.fake.shape.name=ball`` resumed a torus scan killed after 4 of 12 dips: exit 0, the file
    held 4 torus dips and 8 ball dips (reconstructed: profile residual 0.30, volume ratio 1.11). The fake rig's object
    is recorded under ``config.scan``; a real rig's scan records none, and is not compared."""
    def header(shape: dict | None) -> ScanHeader:
        rig = {"name": "fake-grbl", "fake": None if shape is None else {"shape": shape}}
        return ScanHeader(quantity="level_mm", ndim=3, tank_cross_section_mm2=2e4, step_mm=1.0,
                          config={"scan": {"rig": rig, "n_dips": 12}})

    torus = {"_target_": "dipnet.shapes.builtin_shape", "name": "torus", "ndim": 3, "radius": 40.0}
    path = tmp_path / "scan.jsonl"
    with RawScanWriter(path, header(torus), fsync=False) as w:
        _dip(w, 0)
    with pytest.raises(RawScanFileError, match=re.escape(
            "rig.fake.shape.name (config.scan.rig.fake.shape.name) 'torus' -> 'ball'")):
        RawScanWriter(path, header({**torus, "name": "ball"}), fsync=False)
    RawScanWriter(path, header(torus), fsync=False).close()  # the same object resumes
    real = tmp_path / "real.jsonl"
    RawScanWriter(real, header(None), fsync=False).close()
    RawScanWriter(real, header(None), fsync=False).close()
