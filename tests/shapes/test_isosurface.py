"""Iso-surfaces in mm: a ball's mesh is closed, centred and of the ball's volume; a disk's contour its area;
the level that encloses a given volume."""

import math

import numpy as np
import pytest
from scipy import ndimage

from dipnet.core.grid import Grid
from dipnet.shapes import Ball, Disk
from dipnet.shapes.isosurface import enclosed_volume, level_for_volume, volume_to_contours, volume_to_mesh


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


def test_enclosed_volume_is_the_meshs_and_subtracts_holes_in_2d():
    grid = Grid(48, 3, 100.0)
    occupancy = Ball(30.0).occupancy(grid, supersample=2).numpy()
    assert enclosed_volume(occupancy, grid) == pytest.approx(volume_to_mesh(occupancy, grid).volume)
    plane = Grid(64, 2, 100.0)
    ring = Disk(30.0).occupancy(plane, supersample=2).numpy() - Disk(15.0).occupancy(plane, supersample=2).numpy()
    assert enclosed_volume(ring, plane) == pytest.approx(math.pi * (30.0**2 - 15.0**2), rel=0.02)


def test_the_level_for_a_volume_undoes_a_blur():
    # blurring a ball's occupancy moves its 0.5 surface inward (a convex body loses volume);
    # the level that encloses the true volume puts the surface back on the sphere
    grid = Grid(40, 3, 100.0)
    exact = 4 / 3 * math.pi * 30.0**3
    blurred = ndimage.gaussian_filter(Ball(30.0).occupancy(grid, supersample=2).numpy().astype(float), 1.5)
    assert enclosed_volume(blurred, grid) < 0.99 * exact
    level = level_for_volume(blurred, grid, exact)
    assert 0.25 < level < 0.5
    assert enclosed_volume(blurred, grid, level) == pytest.approx(exact, rel=1e-3)
    radii = np.linalg.norm(volume_to_mesh(blurred, grid, level).vertices, axis=1)
    assert abs(radii.mean() - 30.0) < 0.1 * grid.voxel_size


def test_the_level_for_a_volume_stays_in_its_bounds():
    grid = Grid(24, 3, 100.0)
    occupancy = Ball(30.0).occupancy(grid, supersample=2).numpy()
    assert level_for_volume(occupancy, grid, 1e9) == 0.25  # more than any level encloses
    assert level_for_volume(occupancy, grid, 1.0, bounds=(0.3, 0.6)) == 0.6
    with pytest.raises(ValueError, match="increasing"):
        level_for_volume(occupancy, grid, 1.0, bounds=(0.6, 0.3))
    with pytest.raises(ValueError, match="positive"):
        level_for_volume(occupancy, grid, 0.0)
