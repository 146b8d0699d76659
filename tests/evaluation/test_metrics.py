"""IoU, Chamfer / Hausdorff (METRO-style, in truth diagonals), volume error, evaluate()."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.evaluation.metrics import EMPTY_DISTANCE, chamfer_hausdorff, evaluate, iou, surface_points, volume_error
from dipnet.core.reconstruction import Reconstruction


def ball(grid: Grid, centre, radius: float) -> np.ndarray:
    return np.linalg.norm(grid.centers().numpy() - np.asarray(centre, float), axis=-1) < radius


def test_iou_identical_disjoint_and_nested():
    a = np.zeros((10, 10, 10), bool)
    a[:, :, :4] = True
    b = np.zeros_like(a)
    b[:, :, 6:] = True
    c = np.zeros_like(a)
    c[:, :, :8] = True
    assert iou(a, a) == 1.0
    assert iou(a, b) == 0.0
    assert iou(a, c) == pytest.approx(0.5)
    assert iou(torch.from_numpy(a), c) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="shape"):
        iou(a, a[0])


def test_chamfer_of_identical_surfaces_is_zero():
    pts = np.random.default_rng(0).normal(size=(500, 3))
    out = chamfer_hausdorff(pts, pts)
    assert out["chamfer"] == 0.0 and out["hausdorff"] == 0.0 and not out["empty"]


def test_chamfer_and_hausdorff_of_shifted_spheres():
    r, s = 20.0, 2.0
    a = trimesh.creation.icosphere(subdivisions=5, radius=r)
    b = a.copy()
    b.apply_translation([s, 0.0, 0.0])
    out = chamfer_hausdorff(a, b, n_points=20_000, seed=1)
    same = chamfer_hausdorff(a, a, n_points=2000, seed=1)
    assert same["chamfer"] < 1e-9 and same["hausdorff"] < 1e-9  # exact point-to-surface distances
    diag = 2 * r * math.sqrt(3)
    # mean distance from a sphere to the shifted sphere: average of |sqrt(r^2+s^2-2rs u) - r|, u ~ U[-1, 1]
    u = np.linspace(-1, 1, 200_001)
    mean_dist = np.abs(np.sqrt(r**2 + s**2 - 2 * r * s * u) - r).mean()
    assert out["chamfer"] == pytest.approx(mean_dist / diag, rel=0.02)
    assert out["hausdorff"] == pytest.approx(s / diag, rel=0.03)


def test_empty_surface_gives_finite_bad_distance():
    out = chamfer_hausdorff(np.ones((10, 3)), np.zeros((0, 3)))
    assert out == {"chamfer": EMPTY_DISTANCE, "hausdorff": EMPTY_DISTANCE, "empty": True}


def test_volume_error():
    grid = Grid(10)
    vol = np.zeros(grid.shape, bool)
    vol[:5] = True
    true = 500 * grid.voxel_volume
    assert volume_error(vol, true, grid) == pytest.approx(0.0)
    assert volume_error(vol, true / 2, grid) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="positive"):
        volume_error(vol, 0.0, grid)


def test_surface_points_lie_on_the_surface():
    grid = Grid(32)
    pts = surface_points(ball(grid, [5.0, 0.0, -5.0], 25.0), grid, n_points=2000, seed=0)
    assert pts.shape == (2000, 3)
    r = np.linalg.norm(pts - [5.0, 0.0, -5.0], axis=1)
    assert np.abs(r - 25.0).max() < grid.voxel_size
    grid2 = Grid(64, ndim=2)
    pts2 = surface_points(ball(grid2, [5.0, 0.0], 25.0), grid2, n_points=1000, seed=0)
    assert pts2.shape == (1000, 2)
    assert np.abs(np.linalg.norm(pts2 - [5.0, 0.0], axis=1) - 25.0).max() < grid2.voxel_size
    same = surface_points(ball(grid2, [5.0, 0.0], 25.0), grid2, n_points=1000, seed=0)
    np.testing.assert_array_equal(pts2, same)  # seeded


@pytest.mark.parametrize("ndim", [2, 3])
def test_evaluate_perfect_and_empty(ndim):
    grid = Grid(32, ndim=ndim)
    truth = ball(grid, [4.0, -3.0, 2.0][:ndim], 22.0).astype(np.float64)
    good = evaluate(Reconstruction(torch.from_numpy(truth).float(), grid, 0.5), truth, grid, n_points=5000)
    assert good["iou"] == 1.0 and good["chamfer"] < 1e-9 and abs(good["volume_error"]) < 1e-9
    assert good["empty"] is False
    bad = evaluate(Reconstruction(torch.zeros(grid.shape), grid, 0.5), truth, grid, n_points=5000)
    assert bad["iou"] == 0.0 and bad["empty"] is True and bad["volume_error"] == -1.0
    assert bad["chamfer"] == EMPTY_DISTANCE and bad["hausdorff"] == EMPTY_DISTANCE
    assert json.loads(json.dumps(good)) == good and json.loads(json.dumps(bad)) == bad  # JSON-friendly


def test_evaluate_against_a_truth_mesh():
    grid = Grid(40)
    r = 25.0
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=r)
    truth = ball(grid, [0.0, 0.0, 0.0], r).astype(np.float64)
    out = evaluate(Reconstruction(torch.from_numpy(truth), grid, 0.5), truth, grid, truth_mesh=mesh, n_points=5000)
    assert out["iou"] == 1.0
    voxel = grid.voxel_size / (2 * r * math.sqrt(3))  # one voxel, in truth diagonals
    assert out["chamfer"] < 0.25 * voxel and out["hausdorff"] < voxel  # staircase vs exact sphere
    assert abs(out["volume_error"]) < 0.05  # voxelisation against the exact mesh volume
    shifted = evaluate(Reconstruction(torch.from_numpy(truth), grid, 0.5), truth, grid,
                       truth_mesh=mesh.copy().apply_translation([5.0, 0, 0]), n_points=5000)
    assert shifted["hausdorff"] > 4.0 / (2 * r * math.sqrt(3))
