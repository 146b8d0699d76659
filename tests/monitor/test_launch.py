"""scan.py monitor=true (dipnet.monitor.launch): with the port taken the scan stops before anything moves."""

from __future__ import annotations

import socket
import subprocess
import sys

from monitor_helpers import SCAN_OVERRIDES
from script_modules import SCRIPTS


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
