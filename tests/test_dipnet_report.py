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


def test_importing_the_module_runs_nothing(monkeypatch, capsys):
    """Imported (not run), the module only names the entry point: the report's own ``main``."""
    from dipnet import report
    from dipnet.experiments.report import main

    assert report.main is main and capsys.readouterr().out == ""
