"""``python -m dipnet.report JOB_DIR ...`` (dipnet/report.py): the command line of the run report, run as
``-m`` runs it (the module as ``__main__``, in this process)."""

from __future__ import annotations

import runpy
import sys

import pytest

from sweep_fixtures import write_job


def _report(monkeypatch, *args: str) -> int:
    """Run ``python -m dipnet.report ARGS``; its exit code."""
    monkeypatch.setattr(sys, "argv", ["python -m dipnet.report", *args])
    with pytest.raises(SystemExit) as done:
        runpy.run_module("dipnet.report", run_name="__main__")
    return done.value.code


def test_each_job_gets_its_report_and_the_path_is_printed(tmp_path, monkeypatch, capsys):
    jobs = [write_job(tmp_path / name, solver="minnorm", n_dips=n, snr_db=None, seed=0, metrics={"iou": 1 - 1 / n})
            for name, n in (("a", 4), ("b", 8))]
    assert _report(monkeypatch, *map(str, jobs)) == 0
    assert capsys.readouterr().out.split() == [str(job / "report.html") for job in jobs]
    for job in jobs:
        assert "How close to the truth?" in (job / "report.html").read_text()


def test_no_job_directory_is_a_usage_error(monkeypatch, capsys):
    assert _report(monkeypatch) == 2
    err = capsys.readouterr().err
    assert "usage: python -m dipnet.report" in err and "the following arguments are required: jobs" in err


@pytest.mark.parametrize("kind", ["missing", "empty"])
def test_a_folder_that_is_no_run_is_one_error_line_and_no_page(tmp_path, monkeypatch, capsys, kind):
    """A missing folder printed a ``FileNotFoundError`` traceback (exit 1); an empty one (or any folder that is no
    run) got a report.html of nothing, exit 0. Neither the run given before it gets a page."""
    job = write_job(tmp_path / "a", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.5})
    other = tmp_path / "typo"
    if kind == "empty":
        other.mkdir()
    assert _report(monkeypatch, str(job), str(other)) == 2
    err = capsys.readouterr().err
    what = "not a folder" if kind == "missing" else "holds no run"
    assert err.startswith(f"error: {other}: {what}") and err.count("\n") == 1, err
    assert not (job / "report.html").exists() and not (other / "report.html").exists()


def test_importing_the_module_runs_nothing(monkeypatch, capsys):
    """Imported (not run), the module only names the entry point: the report's own ``main``."""
    from dipnet import report
    from dipnet.experiments.report import main

    assert report.main is main and capsys.readouterr().out == ""
