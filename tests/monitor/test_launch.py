"""The scan side (dipnet.monitor.journal, launch): the journal records the dipnet warnings, the runner's
stage with the controller's last status report and the safe-stop message; scan.py monitor=true with the
port taken stops before anything moves."""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import sys
from types import SimpleNamespace

from conftest import SCAN_OVERRIDES
from dipnet.monitor.journal import MonitorJournal, format_report
from dipnet.monitor.tail import JournalTail, journal_path
from dipnet.rig.grbl_dialect import GrblStatus
from script_modules import SCRIPTS


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


def test_scan_with_the_monitor_on_a_taken_port_stops_before_anything_moves(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.run([sys.executable, str(SCRIPTS / "scan.py"), f"hydra.run.dir={tmp_path}", *SCAN_OVERRIDES,
                               "monitor=true", f"monitor_port={port}"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert f"error: cannot serve the monitor on 127.0.0.1:{port}" in proc.stderr
    assert not (tmp_path / "rawscan.jsonl").exists()
