"""The raw scan writer: what it writes reads back, a resumed file goes on, a second writer is refused."""

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
