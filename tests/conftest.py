"""Shared pytest options and fixtures."""

from __future__ import annotations

import io
import logging
import os
import sys
from pathlib import Path

import pytest
import torch

from dipnet.preprocessing.datasets import MESHES_DIR

# helper modules shared by several test folders (sweep_fixtures) live here, beside this file
sys.path.insert(0, str(Path(__file__).parent))
from script_runs import script_run  # noqa: E402,F401  (a fixture: scripts run in this process)

# under pytest-xdist (``-n auto``: one worker per core) each worker computes on one thread, and so do the
# scripts the tests start, unless OMP_NUM_THREADS says otherwise
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-hardware", action="store_true", default=False,
                     help="run tests that need a real dipping rig")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--run-hardware"):
        return
    skip = pytest.mark.skip(reason="needs a real rig: pass --run-hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


#: Markers of the only tests that may skip under ``DIPNET_STRICT_SKIPS=1`` (set by ``.ci/run``):
#: they need a real rig or a browser, which CI may not have. Any other skip fails there.
ALLOWED_SKIP_MARKERS = ("hardware", "browser")


def _strict_skips() -> bool:
    return os.environ.get("DIPNET_STRICT_SKIPS", "") not in ("", "0")


def _fail_unexpected_skip(report: pytest.TestReport | pytest.CollectReport, what: str) -> None:
    reason = report.longrepr[-1] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    report.outcome = "failed"
    report.longrepr = (f"{what} skipped ({reason}); under DIPNET_STRICT_SKIPS=1 only tests marked "
                       f"{' or '.join(ALLOWED_SKIP_MARKERS)} may skip")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    report = outcome.get_result()
    if (report.skipped and _strict_skips() and not hasattr(report, "wasxfail")
            and not any(item.get_closest_marker(m) for m in ALLOWED_SKIP_MARKERS)):
        _fail_unexpected_skip(report, item.nodeid)


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector):
    outcome = yield
    report = outcome.get_result()
    if report.skipped and _strict_skips():  # a module-level skip (e.g. importorskip)
        _fail_unexpected_skip(report, collector.nodeid)


@pytest.fixture(scope="session")
def meshes_dir() -> Path:
    """The bundled example meshes (``dipnet/data/meshes``)."""
    return MESHES_DIR


@pytest.fixture
def console_and_log_file(tmp_path: Path):
    """``(console handler, log file path)``: a console ``StreamHandler`` (its text in ``.stream``) and a
    ``FileHandler`` on the root logger for the test, as Hydra's job logging has them."""
    console, logfile = logging.StreamHandler(io.StringIO()), logging.FileHandler(tmp_path / "job.log")
    root = logging.getLogger()
    for handler in (console, logfile):
        root.addHandler(handler)
    yield console, tmp_path / "job.log"
    for handler in (console, logfile):
        root.removeHandler(handler)
    logfile.close()


@pytest.fixture(autouse=True)
def root_logger_kept():
    """Every test leaves the root logger as it found it: a handler a script added in this process (``tune.py`` and
    the monitor's command line call ``logging.basicConfig``, whose ``StreamHandler`` keeps the test's captured
    ``stderr``) is removed and closed, and the root's level put back. Left in place, every later test's log line
    went to that closed stream as a "Logging error" on the real ``stderr`` (``tests/jobs`` in one process:
    ``test_tuning`` and ``test_warnings_once`` failed; pytest's own capture handlers are its to remove)."""
    root = logging.getLogger()
    before, level = set(root.handlers), root.level
    yield
    for handler in root.handlers[:]:
        if handler not in before and type(handler).__module__ != "_pytest.logging":
            root.removeHandler(handler)
            handler.close()
    root.setLevel(level)
