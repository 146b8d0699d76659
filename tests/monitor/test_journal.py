"""The scan side of the monitor (dipnet.monitor.journal): the journal records the dipnet warnings, the
runner's stage with the controller's last status report, and the safe-stop message."""

from __future__ import annotations

import json
import logging
from types import SimpleNamespace

from dipnet.monitor.journal import MonitorJournal, format_report
from dipnet.monitor.tail import JournalTail, journal_path
from dipnet.rig.grbl_dialect import GrblStatus


def test_the_journal_records_warnings_status_and_the_stop(tmp_path):
    scan = tmp_path / "rawscan.jsonl"
    status = GrblStatus("Idle", None, {"MPos": "0.000,0.000,-24.000", "FS": "0,0"})
    runner = SimpleNamespace(where="orientation 3, reading 12 at 24 mm",
                             controller=SimpleNamespace(last_status=status, dialect="grbl"))
    with MonitorJournal(scan) as journal:
        journal.watch(runner)
        logging.getLogger("dipnet.rig.grbl").warning("late reply %r", "ok")
        logging.getLogger("dipnet.rig").info("not journalled")
        journal.stopped("scan stopped at orientation 3: ...")
    records = [json.loads(line) for line in journal_path(scan).read_text().splitlines()]
    assert [r["type"] for r in records] == ["session", "warning", "stopped", "status"]
    assert records[1]["message"] == "late reply 'ok'" and records[1]["logger"] == "dipnet.rig.grbl"
    assert records[3]["report"] == "<Idle|MPos:0.000,0.000,-24.000|FS:0,0>" and records[3]["state"] == "Idle"
    tail = JournalTail(scan)
    tail.poll()
    assert tail.status["where"] == runner.where
    assert format_report(None) == ""


def test_a_non_finite_number_is_journalled_as_strict_json_null(tmp_path):
    scan = tmp_path / "rawscan.jsonl"
    journal = MonitorJournal(scan)
    journal.write({"type": "status", "stage_mm": float("nan")})
    journal.close()

    def refuse(word):
        raise ValueError(f"not JSON: {word}")

    (record,) = [json.loads(line, parse_constant=refuse) for line in journal_path(scan).read_text().splitlines()]
    assert record["stage_mm"] is None
