"""Following a growing raw scan (dipnet.monitor.tail): a line counts once it is whole, a replaced
file is read again, a malformed line stops the reading with its place named."""

from __future__ import annotations

import json

import pytest

from dipnet.core.rawscan import RawScanFileError, read_rawscan
from dipnet.monitor.tail import JournalTail, ScanTail, journal_path


def test_the_tail_reads_the_scan_as_the_reader_does(recorded_scan):
    tail = ScanTail(recorded_scan)
    assert tail.poll() and not tail.poll()          # everything at once, then nothing new
    raw = read_rawscan(recorded_scan)
    assert [d.k for d in tail.dips] == [o.k for o in raw.orientations] and all(d.complete for d in tail.dips)
    assert [d.values for d in tail.dips] == [o.values.tolist() for o in raw.orientations]
    assert tail.header.rig == raw.header.rig and len(tail.sessions) == 1 and tail.error is None


def test_a_line_being_written_waits_for_its_end(recorded_scan, tmp_path):
    lines = recorded_scan.read_bytes().splitlines(keepends=True)
    path = tmp_path / "rawscan.jsonl"
    path.write_bytes(b"".join(lines[:5]) + lines[5][:20])        # a reading cut mid-line
    tail = ScanTail(path)
    tail.poll()
    n = sum(len(d.values) for d in tail.dips)
    assert tail.truncated and tail.n_lines == 5
    with path.open("ab") as f:
        f.write(lines[5][20:])
    assert tail.poll() and not tail.truncated and sum(len(d.values) for d in tail.dips) == n + 1


def test_a_scan_resumed_after_dying_mid_line_is_followed_on(recorded_scan, tmp_path):
    """The audit's case: a scan died mid-line while the monitor followed it; the resumed run cut the partial line off
    and wrote its session and readings from there, and the tail glued the partial line to the new bytes: "byte ...:
    'value'", and the page stopped reading the scan."""
    from dipnet.core.rawscan_writer import RawScanWriter

    lines = recorded_scan.read_bytes().splitlines(keepends=True)
    path = tmp_path / "rawscan.jsonl"
    path.write_bytes(b"".join(lines[:5]) + lines[5][:20])        # a reading cut mid-line by a crash
    tail = ScanTail(path)
    tail.poll()
    raw = read_rawscan(path)
    with RawScanWriter(path, raw.header, fsync=False) as writer:  # the resumed run
        writer.record_session({"first_k": 0})
        writer.begin_orientation(0, tilt_deg=raw.orientations[0].tilt_deg, spin_deg=raw.orientations[0].spin_deg)
        writer.append_reading(0.0, 150.0, 1.0)
    assert tail.poll() and tail.error is None and not tail.truncated
    resumed = read_rawscan(path)
    assert len(tail.sessions) == len(resumed.sessions) == 2
    assert [d.values for d in tail.dips] == [o.values.tolist() for o in resumed.orientations] == [[150.0]]


def test_a_replaced_file_is_read_from_its_start(recorded_scan, tmp_path):
    path = tmp_path / "rawscan.jsonl"
    path.write_bytes(recorded_scan.read_bytes())
    tail = ScanTail(path)
    tail.poll()
    path.write_bytes(b"".join(recorded_scan.read_bytes().splitlines(keepends=True)[:3]))  # a new, shorter scan
    tail.poll()
    assert tail.n_lines == 3 and len(tail.dips) <= 1


def test_a_malformed_line_is_named_and_ends_the_reading(recorded_scan, tmp_path):
    path = tmp_path / "rawscan.jsonl"
    path.write_bytes(recorded_scan.read_bytes() + b'{"type": "bogus"}\n')
    tail = ScanTail(path)
    tail.poll()
    assert "unknown record type 'bogus'" in tail.error and str(path) in tail.error


def test_the_journal_keeps_events_and_the_newest_status(tmp_path):
    scan = tmp_path / "rawscan.jsonl"
    records = [{"type": "session", "time": 1.0}, {"type": "status", "where": "a", "time": 2.0},
               {"type": "warning", "message": "w", "time": 3.0}, {"type": "status", "where": "b", "time": 4.0}]
    journal_path(scan).write_text("".join(json.dumps(r) + "\n" for r in records) + "not json\n")
    journal = JournalTail(scan)
    assert journal.poll()
    assert journal.status["where"] == "b" and [e["type"] for e in journal.events] == ["session", "warning"]


@pytest.mark.parametrize("line, reason", [
    ('{"type": "reading", "k": 5, "stage_mm": 200.0, "value": NaN, "time_s": 1.0, "flags": []}', "non-finite"),
    ('[1, 2]', "a JSON object with a 'type' field"),
    ('{"type": "orientation", "k": 0, "tilt_deg": 10.0, "spin_deg": 0.0, "meta": {}}', "begun again"),
    ('{"type": "reading", "k": 5, "stage_mm": 0.0, "value": 150.0, "time_s": 1.0, "flags": []}', "backwards"),
])
def test_a_line_the_reader_refuses_ends_the_reading_as_it_does(recorded_scan, tmp_path, line, reason):
    """The tail took a NaN reading, a stage moving back or a completed orientation begun again as recorded (the
    page drew them; the reconstruction refuses the file), and a line that is JSON but no object crashed its thread."""
    lines = recorded_scan.read_bytes().splitlines(keepends=True)
    cut = max(i for i, text in enumerate(lines) if b'"type": "orientation"' in text) + 4   # into the last dip
    path = tmp_path / "rawscan.jsonl"
    path.write_bytes(b"".join(lines[:cut]) + line.encode() + b"\n")
    with pytest.raises(RawScanFileError, match=reason):
        read_rawscan(path)
    tail = ScanTail(path)
    tail.poll()
    assert tail.error is not None and reason in tail.error and str(path) in tail.error
    assert tail.n_lines == cut


def test_a_journal_line_without_what_the_page_needs_is_skipped(tmp_path):
    """A journal line that was JSON but not an event (a list, ``null``, a stop without its message) crashed the page's
    state (AttributeError, KeyError), which the docstring promised to skip."""
    scan = tmp_path / "rawscan.jsonl"
    records = ["[1]", "null", json.dumps({"type": "stopped", "time": 2.0}), json.dumps({"type": "warning"}),
               json.dumps({"type": "warning", "message": "w", "time": 3.0})]
    journal_path(scan).write_text("\n".join(records) + "\n")
    journal = JournalTail(scan)
    assert journal.poll()
    assert [e["message"] for e in journal.events] == ["w"]
