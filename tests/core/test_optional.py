"""Optional dependencies: a missing one is named with the pip extra that installs it."""

from __future__ import annotations

import importlib.metadata
import re
import sys

import numpy as np
import pytest
import trimesh

from dipnet.core.optional import MissingExtraError, optional_import
from dipnet.rig.sensors import ModbusLevelSensor
from dipnet.shapes.mesh import from_trimesh


def block(monkeypatch: pytest.MonkeyPatch, module: str) -> None:
    """Make ``import module`` fail as if the package were not installed."""
    monkeypatch.setitem(sys.modules, module, None)


def test_an_installed_module_is_returned():
    assert optional_import("numpy.linalg", extra="dev", purpose="a test") is np.linalg


def test_a_missing_module_names_its_extra(monkeypatch):
    block(monkeypatch, "minimalmodbus")
    with pytest.raises(ImportError, match=re.escape('a test needs minimalmodbus, which the core install leaves '
                                                    'out: pip install "dipnet[rig]"')) as err:
        optional_import("minimalmodbus", extra="rig", purpose="a test")
    assert isinstance(err.value, MissingExtraError)


def test_a_modbus_sensor_without_the_rig_extra_says_how_to_install_it(monkeypatch):
    block(monkeypatch, "minimalmodbus")
    with pytest.raises(MissingExtraError, match=re.escape('pip install "dipnet[rig]"')):
        ModbusLevelSensor("fakerig://nowhere")


def test_a_mesh_that_needs_repair_without_the_repair_extra_says_how_to_install_it(monkeypatch):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    faces = mesh.faces.copy()
    faces[3] = faces[3][::-1]  # one flipped face: the winding repair needs networkx
    block(monkeypatch, "networkx")
    with pytest.raises(MissingExtraError, match=re.escape('winding of a mesh\'s faces needs networkx, which the core '
                                                          'install leaves out: pip install "dipnet[repair]"')):
        from_trimesh(trimesh.Trimesh(mesh.vertices, faces, process=False))
    # a sound mesh needs no repair, so it loads without the extra
    assert from_trimesh(mesh).volume == pytest.approx(mesh.volume)


def test_overlapping_shells_without_the_repair_extra_say_how_to_install_it(monkeypatch):
    a, b = trimesh.creation.box(extents=[2.0, 2.0, 2.0]), trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    b.apply_translation([1.0, 0.5, 0.0])
    block(monkeypatch, "manifold3d")
    with pytest.raises(MissingExtraError, match=re.escape('merging overlapping mesh shells needs manifold3d')):
        from_trimesh(trimesh.util.concatenate([a, b]))


@pytest.mark.parametrize("extra,packages", [("rig", {"minimalmodbus"}), ("repair", {"networkx", "manifold3d"})])
def test_the_extras_named_in_messages_install_those_packages(extra, packages):
    """The installed metadata (from pyproject.toml) declares each extra with its packages; ``dev``
    pulls them in, so the README's test command has everything."""
    requires = importlib.metadata.requires("dipnet") or []
    declared = {re.split(r"[<>=!~ ;\[]", r)[0].lower() for r in requires if f'extra == "{extra}"' in r}
    assert packages <= declared
    assert any("dipnet[" in r and extra in r and 'extra == "dev"' in r for r in requires)
