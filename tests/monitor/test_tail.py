"""Following a growing raw scan (dipnet.monitor.tail): a line counts once it is whole, a replaced
file is read again, a malformed line stops the reading with its place named."""

from __future__ import annotations

import json

from dipnet.core.rawscan import read_rawscan
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
