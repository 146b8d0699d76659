"""Iso-surfaces in mm: a ball's mesh is closed, centred and of the ball's volume; a disk's contour its area."""

import math

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.shapes import Ball, Disk
from dipnet.shapes.isosurface import volume_to_contours, volume_to_mesh


def test_a_balls_mesh_is_closed_with_the_balls_volume():
    grid = Grid(48, 3, 100.0)
    occupancy = Ball(30.0).occupancy(grid, supersample=2).numpy()
    mesh = volume_to_mesh(occupancy, grid)
    assert mesh.is_watertight and mesh.volume > 0  # outward normals
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 30.0**3, rel=0.03)
    assert np.allclose(mesh.vertices.mean(axis=0), 0.0, atol=0.5)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 30.0).max() < grid.voxel_size


def test_a_disks_contour_encloses_its_area():
    grid = Grid(64, 2, 100.0)
    contours = volume_to_contours(Disk(25.0).occupancy(grid, supersample=2).numpy(), grid)
    assert len(contours) == 1
    x, y = contours[0][:, 0], contours[0][:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    assert area == pytest.approx(math.pi * 25.0**2, rel=0.02)


def test_empty_volumes_and_wrong_dimensions():
    assert len(volume_to_mesh(np.zeros((8, 8, 8)), Grid(8, 3, 10.0)).faces) == 0
    assert volume_to_contours(np.zeros((8, 8)), Grid(8, 2, 10.0)) == []
    with pytest.raises(ValueError, match="3D grid"):
        volume_to_mesh(np.zeros((8, 8)), Grid(8, 2, 10.0))
