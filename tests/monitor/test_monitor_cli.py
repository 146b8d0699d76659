"""scripts/monitor.py (dipnet.monitor.cli): 127.0.0.1 by default, one message per bad input (a port in use,
no scan, no run directory) with exit code 2."""

from __future__ import annotations

import socket

import pytest

from dipnet.monitor import cli
from dipnet.monitor.server import MonitorError, check_port, find_scan
from test_server import free_port


def test_the_default_address_is_the_loopback():
    assert cli.parser().parse_args(["scans/x"]).host == "127.0.0.1"


def test_a_port_in_use_is_one_message(recorded_scan, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(MonitorError, match=f"cannot serve the monitor on 127.0.0.1:{port}: .*choose another"):
            check_port("127.0.0.1", port)
        assert cli.main([str(recorded_scan.parent), "--port", str(port), "--no-recon"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot serve the monitor") and err.count("\n") == 1


def test_a_run_directory_without_a_scan_is_one_message(tmp_path, capsys):
    with pytest.raises(MonitorError, match="holds no scan: expected .*rawscan.jsonl"):
        find_scan(tmp_path)
    assert cli.main([str(tmp_path / "missing"), "--port", str(free_port())]) == 2
    assert "does not exist: give the run directory of a scan" in capsys.readouterr().err
    assert cli.main(["--port", str(free_port())]) == 2
    assert "give either a run directory (RUN) or --replay FILE" in capsys.readouterr().err
