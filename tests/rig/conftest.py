"""Fixtures of the rig tests (here and in fake/): the registered fake world holding the bundled torus."""

from __future__ import annotations

import pytest

from rig_helpers import make_world


@pytest.fixture(scope="module")
def world(meshes_dir):
    """A fake rig holding the bundled torus (radius 42 mm), registered as ``fakerig://testrig``; one per module."""
    return make_world(meshes_dir, "testrig")
