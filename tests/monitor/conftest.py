"""Fixtures of the monitor tests: a small fake-rig scan recorded once per session."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from monitor_helpers import SCAN_OVERRIDES


def scan_config(*overrides: str):
    """The scan config (``conf/scan.yaml``) with the small scan's overrides and ``overrides``."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="scan", overrides=[*SCAN_OVERRIDES, *overrides])


@pytest.fixture(scope="session")
def recorded_scan(tmp_path_factory) -> Path:
    """A finished fake-rig scan (``rawscan.jsonl``); copy it before changing it."""
    from dipnet.jobs.scan import scan_job

    path = tmp_path_factory.mktemp("recorded") / "rawscan.jsonl"
    scan_job(scan_config(), path)
    return path


@pytest.fixture
def scan_copy(recorded_scan, tmp_path) -> Path:
    """A copy of :func:`recorded_scan` in its own run directory."""
    run = tmp_path / "run"
    run.mkdir()
    return Path(shutil.copy(recorded_scan, run / "rawscan.jsonl"))
