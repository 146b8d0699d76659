"""Fixtures of the rig tests (here and in fake/): the registered fake world holding the bundled torus."""

from __future__ import annotations

import pytest

from dipnet.rig.controller import PortLock
from rig_helpers import make_world


@pytest.fixture(autouse=True)
def port_files(tmp_path_factory, monkeypatch):
    """Each test's port locks and rig-wide position-lost markers in a folder of its own, not the machine's
    ``<tmp>/dipnet-port-locks``: a marker that one test's lost position leaves (``replay://``, ``socket://...``)
    must not stop the scans of later tests, or of the next test run, on the same URL."""
    monkeypatch.setattr(PortLock, "directory", tmp_path_factory.mktemp("port-locks"))


@pytest.fixture(scope="module")
def world(meshes_dir):
    """A fake rig holding the bundled torus (radius 42 mm), registered as ``fakerig://testrig``; one per module."""
    return make_world(meshes_dir, "testrig")
