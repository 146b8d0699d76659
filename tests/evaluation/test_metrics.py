"""IoU, Chamfer / Hausdorff (METRO-style, in truth diagonals), volume error, evaluate()."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.core.strict_json import dumps, finite_or_none
from dipnet.evaluation.metrics import (EMPTY_DISTANCE, chamfer_hausdorff, evaluate, false_rates, iou,
                                     reference_check, reference_level, surface_points, volume_error)
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


def test_occupancy_fractions_are_refused_where_a_boolean_volume_is_meant():
    """Before: iou, volume_error and false_rates cast their volumes to bool, so occupancy fractions or a minnorm
    result's raw values counted every non-zero voxel as inside: iou(recon.occupancy, truth occupancy) of a
    16^3 chamber box was 0.342 (0.837 thresholded) and its volume error 3.40 (0.30), with no word."""
    grid = Grid(10)
    truth = ball(grid, (0, 0, 0), 30.0)
    fractions = np.where(truth, 0.9, 0.05)  # a soft reconstruction: nearly every voxel slightly filled
    for call in (lambda: iou(fractions, truth), lambda: iou(truth, torch.from_numpy(fractions)),
                 lambda: volume_error(fractions, float(truth.sum()) * grid.voxel_volume, grid),
                 lambda: false_rates(fractions, truth), lambda: false_rates(truth, fractions)):
        with pytest.raises(ValueError, match=r"boolean volume .* \(0.05 to 0.9\): threshold it first"):
            call()
    with pytest.raises(ValueError, match="no finite value"):
        iou(np.full(grid.shape, np.nan), truth)
    assert iou(fractions > 0.5, truth) == 1.0
    assert iou(truth.astype(np.float32), truth.astype(np.uint8)) == 1.0  # numbers that are all 0 or 1 are booleans
    assert false_rates(fractions > 0.5, truth) == {"false_positive": 0.0, "false_negative": 0.0}


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
    assert chamfer_hausdorff(np.zeros((0, 3)), np.ones((10, 3))) == {"chamfer": None, "hausdorff": None,
                                                                       "empty": True}  # no truth to measure against


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


def test_evaluate_refuses_a_grid_other_than_the_reconstructions():
    """Before: evaluate(recon on Grid(16, 2, 100), truth, Grid(16, 2, 120)) took every voxel of the reconstruction
    for one of the other grid: a 2D disk's volume error +0.403 instead of -0.026 (and IoU 0.708 for 0.917 when
    the truth was voxelised on that grid), with no word."""
    grid, other = Grid(16, ndim=2, extent=100.0), Grid(16, ndim=2, extent=120.0)
    truth = ball(grid, [0.0, 0.0], 30.0)
    recon = Reconstruction(torch.from_numpy(truth).float(), grid, 0.5)
    with pytest.raises(ValueError, match=r"the reconstruction is on Grid\(n=16, ndim=2, extent=100.0\), the truth on "
                                         r"Grid\(n=16, ndim=2, extent=120.0\).*shape.occupancy\(reconstruction.grid\)"):
        evaluate(recon, ball(other, [0.0, 0.0], 30.0), other, n_points=500)
    assert evaluate(recon, truth, Grid(16, ndim=2, extent=100.0), n_points=500)["iou"] == 1.0


def test_evaluate_refuses_a_truth_outside_the_occupancy_fractions():
    """Before: a 0/255 mask as the truth scored IoU 1.0 but volume error -0.996 and Chamfer 0.026 for a perfect
    2D reconstruction (0 and 0.0 with the mask in [0, 1]): its volume was read as 255 times the object's."""
    grid = Grid(16, ndim=2)
    truth = ball(grid, [0.0, 0.0], 30.0)
    recon = Reconstruction(torch.from_numpy(truth).float(), grid, 0.5)
    with pytest.raises(ValueError,
                       match=r"fractions in \[0, 1\], got 0 to 255: .* \(a 0/255 mask\? divide it by 255\)"):
        evaluate(recon, truth.astype(np.uint8) * 255, grid, n_points=500)
    with pytest.raises(ValueError, match=r"got 1 to 1 and NaN or inf"):
        evaluate(recon, np.where(truth, 1.0, np.nan), grid, n_points=500)
    assert evaluate(recon, truth.astype(np.uint8), grid, n_points=500)["volume_error"] == 0.0


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


@pytest.mark.parametrize("ndim", [2, 3])
def test_a_truth_smaller_than_the_grid_resolves_has_null_distances_and_a_warning(ndim):
    """Before: Chamfer and Hausdorff 1.0 (the stand-in of an empty surface) against a truth with no surface."""
    grid = Grid(24, ndim=ndim, extent=200.0)
    truth = np.zeros(grid.shape)
    truth[(12,) * ndim] = 0.3  # a 7 mm ball fills under half of an 8.3 mm voxel
    recon = Reconstruction(torch.from_numpy(truth).float(), grid, 0.05)
    with warnings.catch_warnings(record=True) as caught:  # one recorder: nested pytest.warns differ before pytest 8
        warnings.simplefilter("always")
        out = evaluate(recon, truth, grid, n_points=500)
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert any("smaller than the grid resolves, so Chamfer and Hausdorff are null; use a smaller extent_mm or a "
               "higher resolution" in m for m in messages), messages
    assert any("IoU and the false rates are undefined" in m for m in messages), messages
    assert out["chamfer"] is None and out["hausdorff"] is None and math.isnan(out["iou"])
    assert json.loads(dumps(out)) == finite_or_none(out)


def test_iou_and_false_rates_against_an_empty_reference_are_undefined():
    """Before: iou(empty, empty) was 1.0 and the false rates 0.0, a perfect score for a run that lost everything."""
    empty, some = np.zeros((6, 6, 6), bool), np.zeros((6, 6, 6), bool)
    some[2:4, 2:4, 2:4] = True
    assert math.isnan(iou(empty, empty)) and math.isnan(iou(some, empty))
    assert iou(empty, some) == 0.0
    rates = false_rates(empty, empty)
    assert math.isnan(rates["false_positive"]) and math.isnan(rates["false_negative"])
    assert false_rates(empty, some) == {"false_positive": 0.0, "false_negative": 1.0}


def test_a_truth_thinner_than_a_voxel_gets_no_iou_but_a_reason():
    """An 80 x 80 x 0.5 mm plate at 24 voxels of 5.7 mm: no voxel of the truth is inside, nor of the result."""
    grid = Grid(24, extent=137.0)
    plate = trimesh.creation.box(extents=[80.0, 80.0, 0.5])
    recon = Reconstruction(torch.zeros(grid.shape), grid, 0.5)
    with pytest.warns(UserWarning, match="the truth is thinner than a voxel at this resolution "
                                         r"\(24 voxels of 5.71 mm per axis\).*IoU and the false rates are undefined"):
        out = evaluate(recon, np.zeros(grid.shape), grid, truth_mesh=plate, n_points=500)
    assert math.isnan(out["iou"]) and out["empty"] is True
    assert out["overlap_undefined"].startswith("the truth is thinner than a voxel at this resolution")
    assert json.loads(dumps(out))["iou"] is None


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


def test_chamfer_averages_both_directions_of_an_asymmetric_pair():
    """Truth: the segment (0,0)-(10,0); other: the single point (0,1). From the segment to the
    point the mean distance is (1/10) * integral_0^10 sqrt(x^2 + 1) dx = [x sqrt(x^2+1) + asinh x] / 20
    over [0, 10]; from the point to the segment it is 1. A one-sided Chamfer gives one of the two."""
    segment, point = [np.array([[0.0, 0.0], [10.0, 0.0]])], np.array([[0.0, 1.0]])
    to_point = (10 * math.sqrt(101) + math.asinh(10)) / 20  # 5.1748 mm
    out = chamfer_hausdorff(segment, point, n_points=20_000, seed=3)
    diag = 10.0  # the truth's bounding box: the segment
    assert out["chamfer"] == pytest.approx((to_point + 1.0) / 2 / diag, rel=0.01)
    assert out["hausdorff"] == pytest.approx(math.sqrt(101) / diag, rel=1e-3)  # the far end to the point


def test_chamfer_of_point_sets_is_exact_in_both_directions():
    """Truth {0, 10} and other {1, 2, 3} on the x axis: truth -> other distances 1 and 7 (mean 4),
    other -> truth 1, 2, 3 (mean 2); the truth's diagonal is 10 (the other's, 2, when swapped)."""
    on_x = lambda *xs: np.array([[x, 0.0, 0.0] for x in xs])  # noqa: E731
    truth, other = on_x(0.0, 10.0), on_x(1.0, 2.0, 3.0)
    out = chamfer_hausdorff(truth, other)
    assert out["chamfer"] == pytest.approx((4 + 2) / 2 / 10) and out["hausdorff"] == pytest.approx(7 / 10)
    swapped = chamfer_hausdorff(other, truth)
    assert swapped["chamfer"] == pytest.approx((2 + 4) / 2 / 2) and swapped["hausdorff"] == pytest.approx(7 / 2)


def test_reference_level_keeps_the_voxels_that_hold_the_exact_volume():
    """An axis-aligned box 4.9 voxels wide, centred on an 8-voxel grid: 1D occupancy
    [0, .45, 1, 1, 1, 1, .45, 0], in 3D its outer product (exact, so its sum is the exact volume
    4.9^3 voxels). Thresholds: above 0.5 only the 4^3 = 64 core voxels (-46%); between the edge
    value .45^2 = .2025 and the face value .45 the core and the 6 x 16 face voxels, 160 (+36%), the
    closest count; below .2025 also the edges (208). So the level is the midpoint .32625, not 0.5."""
    grid = Grid(8, 3, 8.0)  # 1 mm voxels
    profile = np.array([0, 0.45, 1, 1, 1, 1, 0.45, 0])
    occupancy = np.einsum("i,j,k->ijk", profile, profile, profile)
    exact = 4.9**3 * grid.voxel_volume
    level = reference_level(occupancy, grid, exact)
    assert level == pytest.approx((0.45 + 0.45**2) / 2)
    assert (occupancy > level).sum() == 64 + 6 * 16 and (occupancy > 0.5).sum() == 64
    with pytest.warns(UserWarning, match=r"\+36\.0% off the exact volume"):  # coarse: it says so
        check = reference_check(occupancy, grid, exact, level)
    assert check["truth_voxel_volume_error"] == pytest.approx(0.0, abs=1e-12)
    assert check["truth_binary_volume_error"] == pytest.approx(160 / 4.9**3 - 1)


def test_reference_level_of_a_binary_truth_is_any_level_between_its_values():
    grid = Grid(8, 3, 8.0)
    truth = np.zeros(grid.shape)
    truth[2:6, 2:6, 2:6] = 1.0
    level = reference_level(truth, grid, 64 * grid.voxel_volume)
    assert 0.0 < level < 1.0 and (truth > level).sum() == 64


def test_evaluate_names_arguments_in_the_wrong_order_or_a_shape_for_the_truth():
    """Before: "AttributeError: 'Tensor' object has no attribute 'grid'" (the truth first) and "float() argument must be
    a string or a real number, not 'Ball'" (a shape for the truth)."""
    from dipnet.shapes import Ball

    grid = Grid(8, 3, 40.0)
    truth = Ball(10.0).occupancy(grid)
    recon = Reconstruction(truth, grid)
    with pytest.raises(TypeError, match=r"takes a Reconstruction .* got Tensor and Reconstruction: voxelise"):
        evaluate(truth, recon, grid)
    with pytest.raises(TypeError, match=r"got Reconstruction and Ball: voxelise a true shape with shape.occupancy"):
        evaluate(recon, Ball(10.0), grid)
    with pytest.raises(TypeError, match="grid must be a dipnet.Grid"):
        evaluate(recon, truth, 8)
