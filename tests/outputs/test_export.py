"""Marching-cubes meshes, contours and mesh files in the grid's mm convention."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from dipnet.outputs.export import save_mesh
from dipnet.shapes.isosurface import volume_to_contours, volume_to_mesh
from dipnet.core.grid import Grid

CENTRE = np.array([10.0, -6.0, 4.0])  # (x, y, z) mm: off-centre, distinct per axis
RADIUS = 20.0


def voxel_ball(grid: Grid, centre=CENTRE, radius=RADIUS) -> np.ndarray:
    return np.linalg.norm(grid.centers().numpy() - centre[: grid.ndim], axis=-1) < radius


def test_ball_mesh_volume_position_and_outward_normals():
    grid = Grid(40)
    vol = voxel_ball(grid)
    mesh = volume_to_mesh(vol, grid)
    assert mesh.is_watertight
    assert mesh.volume > 0
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.05)
    assert mesh.volume == pytest.approx(vol.sum() * grid.voxel_volume, rel=0.05)
    # (z, y, x) arrays -> (x, y, z) mm vertices: the centre comes back where it was put
    np.testing.assert_allclose(mesh.vertices.mean(0), CENTRE, atol=grid.voxel_size / 2)
    radial = mesh.triangles_center - CENTRE
    assert (np.einsum("ij,ij->i", mesh.face_normals, radial) > 0).mean() > 0.99


def test_surface_touching_the_border_is_closed():
    grid = Grid(12)
    mesh = volume_to_mesh(np.ones(grid.shape), grid)
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.bounds[1].max() <= grid.extent / 2


def test_level_and_empty_volume():
    grid = Grid(16)
    vol = voxel_ball(grid, np.zeros(3), 25.0).astype(float) * 0.3
    assert len(volume_to_mesh(vol, grid, level=0.5).faces) == 0
    assert volume_to_mesh(vol, grid, level=0.15).volume > 0
    with pytest.raises(ValueError, match="shape"):
        volume_to_mesh(np.zeros((8, 8, 8)), grid)
    with pytest.raises(ValueError, match="2D"):
        volume_to_mesh(np.zeros((16, 16)), Grid(16, ndim=2))


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_save_mesh_round_trip(tmp_path, suffix):
    grid = Grid(20)
    mesh = volume_to_mesh(voxel_ball(grid), grid)
    path = save_mesh(mesh, tmp_path / f"ball{suffix}")
    back = trimesh.load(path, force="mesh")
    assert back.volume == pytest.approx(mesh.volume, rel=1e-4)


def test_save_mesh_rejects_unknown_suffix(tmp_path):
    with pytest.raises(ValueError, match="unsupported mesh format"):
        save_mesh(trimesh.creation.box(), tmp_path / "box.xyz")


def test_disk_contours_in_mm():
    grid = Grid(64, ndim=2)
    lines = volume_to_contours(voxel_ball(grid), grid)
    assert len(lines) == 1
    c = lines[0]
    np.testing.assert_allclose(c[0], c[-1])  # closed
    np.testing.assert_allclose(c.mean(0), CENTRE[:2], atol=grid.voxel_size / 2)
    r = np.linalg.norm(c - CENTRE[:2], axis=1)
    assert np.abs(r - RADIUS).max() < grid.voxel_size
    assert volume_to_contours(np.zeros(grid.shape), grid) == []
