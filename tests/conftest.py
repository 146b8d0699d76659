"""Shared pytest options and fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from dipnet.datasets import MESHES_DIR


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


@pytest.fixture(scope="session")
def meshes_dir() -> Path:
    """The bundled example meshes (``dipnet/data/meshes``)."""
    return MESHES_DIR
