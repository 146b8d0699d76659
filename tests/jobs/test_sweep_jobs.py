"""Sweep jobs: a failing job writes error.txt and returns None; Ctrl-C still stops; one short job line."""

import pytest

from dipnet.jobs.sweep_jobs import ERROR_FILE, guarded_job
from dipnet.outputs.summary import headline


def test_a_finished_job_returns_its_value(tmp_path):
    assert guarded_job(lambda: 0.25, tmp_path) == 0.25
    assert not (tmp_path / ERROR_FILE).exists()


def test_a_failed_job_writes_its_error_and_returns_none(tmp_path):
    def fail():
        raise ValueError("resolution must be\n an integer")

    assert guarded_job(fail, tmp_path / "job") is None
    text = (tmp_path / "job" / ERROR_FILE).read_text()
    assert text.startswith("ValueError: resolution must be an integer\n\n") and "Traceback" in text
    assert guarded_job(lambda: (_ for _ in ()).throw(SystemExit(2)), tmp_path / "exit") is None


def test_ctrl_c_is_not_swallowed(tmp_path):
    def interrupt():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        guarded_job(interrupt, tmp_path)


def test_the_job_line_keeps_the_headline_numbers_in_order():
    line = headline({"seconds": 1.23456, "iou": 0.912345, "other": 3, "consistency": "consistent"})
    assert line == "IoU 0.912, 1.2 s, consistent"
