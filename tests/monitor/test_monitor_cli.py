"""scripts/monitor.py (dipnet.monitor.cli): 127.0.0.1 by default, one message per bad input (a port in use,
no scan, no run directory) with exit code 2; Ctrl-C stops it in one line, exit code 130."""

from __future__ import annotations

import socket
import signal
import tempfile

import pytest

from dipnet.monitor import cli, server
from dipnet.monitor.server import MonitorError, check_port, find_scan
from dipnet.preprocessing.datasets import CATS_CSV
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


@pytest.mark.parametrize("name", ["measurement.npz", "recording.csv"])
def test_a_file_that_is_not_a_scan_is_named_as_such(tmp_path, name):
    path = tmp_path / name
    path.write_text("x")
    with pytest.raises(MonitorError, match=f"{name} is a file, not a scan: .* plays with --replay FILE") as info:
        find_scan(path)
    assert "rawscan.jsonl (written" not in str(info.value)  # not the wrong path foo.npz/rawscan.jsonl


@pytest.mark.parametrize("port", [99999, 0, -1])
def test_a_port_out_of_range_is_one_message(tmp_path, capsys, port):
    with pytest.raises(MonitorError, match=f"the monitor's port must be 1-65535, got {port}"):
        check_port("127.0.0.1", port)
    assert cli.main([str(tmp_path), "--port", str(port), "--no-recon"]) == 2
    err = capsys.readouterr().err
    assert err == f"error: the monitor's port must be 1-65535, got {port} (--port / monitor_port=)\n"


@pytest.mark.parametrize("option, message", [
    (["--resolution", "0"], "--resolution must be an integer in [4, 256] (voxels per axis of a reconstruction "
                            "re-solved every --every dips), got 0"),
    (["--resolution", "100000"], "--resolution must be an integer in [4, 256] (voxels per axis of a reconstruction "
                                 "re-solved every --every dips), got 100000"),
    (["--extent-mm", "-5"], "--extent-mm must be a positive number (mm), got -5.0"),
    (["--extent-mm", "inf"], "--extent-mm must be a positive number (mm), got inf"),
    (["--every", "0"], "--every must be a positive number of dips, got 0"),
    (["--speed", "0"], "--speed must be positive (inf: at once), got 0.0"),
])
def test_options_out_of_range_are_refused_up_front(tmp_path, capsys, option, message):
    assert cli.main([str(tmp_path), "--port", str(free_port()), *option]) == 2
    assert capsys.readouterr().err == f"error: {message}\n"


def test_ctrl_c_stops_a_replay_in_one_line_exit_130_and_removes_its_scratch_copy(tmp_path, capsys, monkeypatch):
    """Ctrl-C exited 0 and left the replay's /tmp/dipnet-replay-XXXX folder behind."""
    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(server, "serve", ctrl_c)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where the replay's scratch copy goes
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--replay", str(CATS_CSV), "--speed", "inf", "--no-recon", "--port", str(free_port())])
    assert exit_.value.code == 130
    assert capsys.readouterr().err == ("interrupted: monitor stopped; to show it again: python scripts/monitor.py "
                                       f"--replay {CATS_CSV}\n")
    assert list(tmp_path.iterdir()) == []


def test_sigterm_ends_it_through_its_cleanup_with_exit_143(tmp_path, monkeypatch):
    """scan.py monitor=true ends the monitor with SIGTERM, which uvicorn re-raises after its shutdown: the default
    handler ended the process before its cleanup, so the reconstruction worker's semaphores leaked (the resource
    tracker's warning) and a replay's scratch copy stayed."""
    def terminate(*args, **kwargs):
        signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(server, "serve", terminate)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--replay", str(CATS_CSV), "--speed", "inf", "--no-recon", "--port", str(free_port())])
    assert exit_.value.code == 128 + signal.SIGTERM
    assert list(tmp_path.iterdir()) == []   # the ExitStack ran
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL   # the handler is the monitor's only while it runs
