"""2D shapes: polygons with holes, the disk, the elephant, and projected mesh silhouettes."""

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.shapes import Disk, PolygonShape, ShapeError, elephant, from_trimesh, project_mesh
from dipnet.shapes.silhouettes import signed_area


def unit_directions(k: int, seed: int) -> torch.Tensor:
    v = torch.randn(k, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return v / v.norm(dim=1, keepdim=True)


def square(c, a):
    return np.array([[c[0] - a, c[1] - a], [c[0] + a, c[1] - a], [c[0] + a, c[1] + a],
                     [c[0] - a, c[1] + a]])


def test_rings_follow_even_odd_rule_in_any_orientation():
    """Outer 40x40 square, a 20x20 hole, an 8x8 island in the hole; orientations as given."""
    rings = [square((0, 0), 20), square((0, 0), 10)[::-1], square((0, 0), 4)]
    for flip in (False, True):
        shape = PolygonShape([r[::-1] if flip else r for r in rings])
        assert shape.volume == pytest.approx(1600 - 400 + 64)
        assert [signed_area(r) > 0 for r in shape.rings] == [True, False, True]
        inside = shape.contains(np.array([[0.0, 0.0], [7.0, 0.0], [15.0, 15.0], [25.0, 0.0]]))
        assert inside.tolist() == [True, False, True, False]
        up = torch.tensor([[0.0, 1.0]], dtype=torch.float64)
        v = shape.volume_below(up, torch.tensor([-20.0, 0.0, 20.0]))[0]
        torch.testing.assert_close(v, torch.tensor([0.0, shape.volume / 2, shape.volume],
                                                   dtype=torch.float64))


def test_random_polygon_area_is_shoelace_and_dips_consistent():
    rng = np.random.default_rng(0)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 30))
    radii = rng.uniform(10, 30, 30)
    ring = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)  # star-shaped
    x, y = ring.T
    shoelace = 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    shape = PolygonShape([ring])
    assert shape.volume == pytest.approx(shoelace, rel=1e-12)
    v = shape.volume_below(unit_directions(16, 1), torch.linspace(-31, 31, 63))
    assert (v[:, 0] == 0).all() and (v.diff(dim=1) >= -1e-9).all()
    torch.testing.assert_close(v[:, -1], torch.full((16,), shoelace, dtype=torch.float64))
    grid = Grid(96, 2, 100.0)
    area = shape.occupancy(grid, supersample=2).sum().item() * grid.voxel_volume
    assert area == pytest.approx(shoelace, rel=0.02)


def test_disk_closed_form_against_fine_polygon():
    r, c = 25.0, np.array([3.0, -4.0])
    disk = Disk(r, center=c)
    assert disk.volume == pytest.approx(np.pi * r**2)
    t = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    fine = PolygonShape([c + r * np.stack([np.cos(t), np.sin(t)], axis=1)])
    d, h = unit_directions(6, 2), torch.linspace(-35, 35, 71)
    torch.testing.assert_close(disk.volume_below(d, h), fine.volume_below(d, h),
                               rtol=0, atol=1e-5 * disk.volume)
    grid = Grid(64, 2, 100.0)
    area = disk.occupancy(grid, supersample=2).sum().item() * grid.voxel_volume
    assert area == pytest.approx(np.pi * r**2, rel=0.01)


def test_elephant_is_a_centred_simple_polygon():
    shape = elephant(40.0)
    assert shape.radius() == pytest.approx(40.0) and len(shape.rings) == 1
    assert shape.volume == pytest.approx(signed_area(shape.rings[0]))
    grid = Grid(128, 2, 100.0)
    occ = shape.occupancy(grid, supersample=2)
    assert occ.sum().item() * grid.voxel_volume == pytest.approx(shape.volume, rel=0.02)
    centroid = (grid.centers() * occ[..., None]).sum(dim=(0, 1)) / occ.sum()
    assert centroid.norm() < grid.voxel_size


def test_projected_ball_is_a_disk_of_the_right_area():
    ball = from_trimesh(trimesh.creation.icosphere(subdivisions=4, radius=30.0), center=False)
    for axis in ("x", "y", "z"):
        silhouette = project_mesh(ball, axis=axis, pixels=512)
        assert len(silhouette.rings) == 1
        assert silhouette.volume == pytest.approx(np.pi * 30.0**2, rel=0.01)
        assert silhouette.radius() == pytest.approx(30.0, rel=0.01)


def test_projected_torus_keeps_its_hole():
    mesh = trimesh.creation.torus(major_radius=30.0, minor_radius=10.0, major_sections=64,
                                  minor_sections=32)
    torus = from_trimesh(mesh, center=False)
    top = project_mesh(torus, axis="z", pixels=512)
    assert len(top.rings) == 2
    assert not top.contains(np.array([[0.0, 0.0]]))[0] and top.contains(np.array([[30.0, 0.0]]))[0]
    assert top.volume == pytest.approx(np.pi * (40.0**2 - 20.0**2), rel=0.01)
    side = project_mesh(torus, axis="x", pixels=512)  # a stadium: no hole
    assert len(side.rings) == 1
    assert side.volume == pytest.approx(80.0 * 20.0 - (4 - np.pi) * 10.0**2, rel=0.01)


def test_polygon_errors():
    with pytest.raises(ShapeError, match="area"):
        PolygonShape([np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])])
    with pytest.raises(ShapeError, match="shape"):
        PolygonShape([np.zeros((4, 3))])
    with pytest.raises(ValueError, match="axis"):
        project_mesh(from_trimesh(trimesh.creation.box()), axis="w")
