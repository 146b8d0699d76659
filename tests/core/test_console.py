"""An entry point's last line: shown once on the terminal, kept in the log file; Ctrl-C's exit code."""

import io
import logging

import pytest

from dipnet.core.console import interrupted, report


def test_ctrl_c_exits_130_saying_how_to_resume(capsys):
    with pytest.raises(SystemExit) as exit_info, interrupted(lambda: "rerun the same command"):
        raise KeyboardInterrupt
    assert exit_info.value.code == 130 and capsys.readouterr().err == "interrupted: rerun the same command\n"


def test_a_report_is_shown_once_and_kept_by_every_handler_but_the_console(tmp_path, capsys):
    """A console handler (Hydra's on stdout) showed the line a second time; a file handler must keep it."""
    console, logfile = logging.StreamHandler(io.StringIO()), logging.FileHandler(tmp_path / "job.log")
    root = logging.getLogger()
    for handler in (console, logfile):
        root.addHandler(handler)
    try:
        report("error: bad option")
        with pytest.raises(SystemExit), interrupted(lambda: "rerun"):
            raise KeyboardInterrupt
    finally:
        for handler in (console, logfile):
            root.removeHandler(handler)
        logfile.close()
    assert console.stream.getvalue() == ""
    assert (tmp_path / "job.log").read_text() == "error: bad option\ninterrupted: rerun\n"
    assert capsys.readouterr().err == "error: bad option\ninterrupted: rerun\n"
