"""Sweep jobs: a failing job writes error.txt and returns None; Ctrl-C still stops; one summary line."""

import pytest

from dipnet.jobs.sweep_jobs import ERROR_FILE, guarded_job, job_summary


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


def test_the_summary_keeps_the_known_metrics_in_order():
    assert job_summary({"seconds": 1.23456, "iou": 0.912345, "other": 3, "empty": False}) == "iou=0.9123 seconds=1.235"
    assert job_summary({"iou": 1}, keys=("iou",)) == "iou=1"
