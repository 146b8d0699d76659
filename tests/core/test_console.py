"""An entry point's last line: shown once on the terminal, kept in the log file; Ctrl-C's exit code."""

import pytest

from dipnet.core.console import interrupted, report


def test_ctrl_c_exits_130_saying_how_to_resume(capsys):
    with pytest.raises(SystemExit) as exit_info, interrupted(lambda: "rerun the same command"):
        raise KeyboardInterrupt
    assert exit_info.value.code == 130 and capsys.readouterr().err == "interrupted: rerun the same command\n"


def test_a_report_is_shown_once_and_kept_by_every_handler_but_the_console(console_and_log_file, capsys):
    """A console handler (Hydra's on stdout) showed the line a second time; a file handler must keep it."""
    console, log_file = console_and_log_file
    report("error: bad option")
    with pytest.raises(SystemExit), interrupted(lambda: "rerun"):
        raise KeyboardInterrupt
    assert console.stream.getvalue() == ""
    assert log_file.read_text() == "error: bad option\ninterrupted: rerun\n"
    assert capsys.readouterr().err == "error: bad option\ninterrupted: rerun\n"
