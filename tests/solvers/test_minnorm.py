"""The paper's linear baseline: minimum-norm / Tikhonov least squares, then Otsu."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.evaluation.metrics import iou
from dipnet.operators import make_operator
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.solvers.minnorm import LSMRSolver, LSQRSolver, MinNormSolver, operator_matrix, otsu_threshold


def disk_area_below(t: np.ndarray, centre_height: float, radius: float) -> np.ndarray:
    """Area (mm^2) of a disk below the line at height ``t`` (circular segment, closed form)."""
    s = np.clip(t - centre_height, -radius, radius)
    return radius**2 * np.arccos(-s / radius) + s * np.sqrt(radius**2 - s**2)


def measurement_for(op, profiles) -> DipMeasurement:
    k = op.n_orientations
    return DipMeasurement(op.directions, profiles, op.slab_thickness, op.slab_edges()[:1].expand(k))


def analytic_disk(op, centre: np.ndarray, radius: float) -> DipMeasurement:
    """Exact slab areas of a disk (no voxelisation: not the solver's own model)."""
    edges = op.slab_edges().numpy()
    heights = op.directions.numpy() @ centre  # (K,)
    cum = disk_area_below(edges[None, :], heights[:, None], radius)
    return measurement_for(op, np.diff(cum, axis=1))


@pytest.mark.parametrize("method", ["cholesky", "lsmr"])
def test_recovers_disk_from_analytic_profiles(method):
    grid = Grid(64, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(20)))
    centre, radius = np.array([8.0, -5.0]), 28.0
    truth = (grid.centers().numpy() - centre).__pow__(2).sum(-1) < radius**2
    rec = MinNormSolver(method=method, progress=False).solve(analytic_disk(op, centre, radius), op)
    assert iou(rec.binary, truth) >= 0.9
    assert rec.occupancy.shape == grid.shape and rec.occupancy.dtype == torch.float32
    assert rec.info["method"] == method and rec.info["relative_residual"] < 0.05
    assert 0.2 < rec.threshold < 0.8  # occupancy scale: no voxel-volume factor left over


def _tiny_problem(seed: int = 0):
    grid = Grid(12, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(5)), n_slabs=10)
    mat = operator_matrix(op).toarray()
    rng = np.random.default_rng(seed)
    g = rng.normal(size=mat.shape[0]) * mat.sum(1).mean()  # inconsistent data: a least-squares problem
    return grid, op, mat, g


def test_methods_agree_with_pseudo_inverse():
    grid, op, mat, g = _tiny_problem()
    meas = measurement_for(op, torch.from_numpy(g.reshape(op.profile_shape)))
    expected = np.linalg.pinv(mat, rcond=1e-10) @ g  # minimum-norm least-squares solution
    scale = np.linalg.norm(expected)
    chol = MinNormSolver(method="cholesky", tikhonov=0.0, progress=False).solve(meas, op)
    assert chol.info["factorisation"] == "eigh-pinv"
    np.testing.assert_allclose(chol.occupancy.double().numpy().ravel(), expected, atol=1e-5 * scale)
    for solver in (LSQRSolver(tikhonov=0.0, atol=1e-12, btol=1e-12, iter_lim=5000, progress=False),
                   LSMRSolver(tikhonov=0.0, atol=1e-12, btol=1e-12, iter_lim=5000, progress=False)):
        rec = solver.solve(meas, op)
        np.testing.assert_allclose(rec.occupancy.double().numpy().ravel(), expected, atol=1e-4 * scale)
        # minimum norm: no component in B's null space, i.e. the solution lies in range(B^T)
        f = rec.occupancy.double().numpy().ravel()
        coeffs, *_ = np.linalg.lstsq(mat.T, f, rcond=None)
        assert np.linalg.norm(mat.T @ coeffs - f) <= 1e-4 * np.linalg.norm(f)


def test_tikhonov_matches_closed_form():
    grid, op, mat, g = _tiny_problem(seed=1)
    meas = measurement_for(op, torch.from_numpy(g.reshape(op.profile_shape)))
    tik = 1e-2
    chol = MinNormSolver(method="cholesky", tikhonov=tik, progress=False).solve(meas, op)
    s = chol.info["shift"]
    assert s == pytest.approx(tik * np.mean(np.sum(mat**2, axis=1)), rel=1e-12)
    assert chol.info["factorisation"] == "cholesky"
    expected = np.linalg.solve(mat.T @ mat + s * np.eye(mat.shape[1]), mat.T @ g)
    got = chol.occupancy.double().numpy().ravel()
    np.testing.assert_allclose(got, expected, atol=1e-5 * np.linalg.norm(expected))
    # the iterative methods damp with their own (estimated) weight: compare to its closed form
    lsmr = MinNormSolver(method="lsmr", tikhonov=tik, atol=1e-12, btol=1e-12, iter_lim=5000,
                         progress=False).solve(meas, op)
    s_it = lsmr.info["damp"] ** 2
    assert s_it == pytest.approx(s, rel=0.25)  # Hutchinson estimate of mean(diag(B B^T))
    expected_it = np.linalg.solve(mat.T @ mat + s_it * np.eye(mat.shape[1]), mat.T @ g)
    np.testing.assert_allclose(lsmr.occupancy.double().numpy().ravel(), expected_it,
                               atol=1e-4 * np.linalg.norm(expected_it))


def test_auto_picks_method_by_size():
    grid = Grid(16, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(6)))
    meas = analytic_disk(op, np.zeros(2), 5.0)
    small = MinNormSolver(method="auto", max_cholesky_rows=10_000, progress=False).solve(meas, op)
    large = MinNormSolver(method="auto", max_cholesky_rows=10, iter_lim=50, progress=False).solve(meas, op)
    assert small.info["method"] == "cholesky" and large.info["method"] == "lsmr"
    assert 0 < large.info["iterations"] <= 50


def test_matrix_of_backend_without_sparse_form():
    grid = Grid(10, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(4)), backend="rotate_sum")
    assert not hasattr(op, "to_sparse")
    x = torch.rand(grid.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    np.testing.assert_allclose(operator_matrix(op) @ x.numpy().ravel(), op(x).numpy().ravel(),
                               rtol=1e-6, atol=1e-9 * float(op(x).abs().max()))


def test_otsu_separates_bimodal_values():
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0.0, 0.08, 4000), rng.normal(1.0, 0.08, 1000)])
    t = otsu_threshold(values)
    assert 0.2 < t < 0.8
    assert ((values > t) == (np.arange(values.size) >= 4000)).mean() > 0.999
    assert otsu_threshold(np.full(10, 0.25)) == 0.25


def test_zero_measurement_gives_empty_reconstruction():
    grid = Grid(16, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(5)))
    rec = MinNormSolver(progress=False).solve(measurement_for(op, torch.zeros(op.profile_shape)), op)
    assert not rec.binary.any() and math.isfinite(rec.threshold)


def test_fixed_threshold_and_bad_options():
    grid = Grid(16, ndim=2)
    op = make_operator(grid, directions_2d(angles_2d(5)))
    rec = MinNormSolver(threshold=0.3, progress=False).solve(analytic_disk(op, np.zeros(2), 20.0), op)
    assert rec.threshold == 0.3
    with pytest.raises(ValueError, match="method"):
        MinNormSolver(method="svd")
    with pytest.raises(ValueError, match="tikhonov"):
        MinNormSolver(tikhonov=-1.0)
    with pytest.raises(ValueError, match="tikhonov must be a finite number"):
        MinNormSolver(tikhonov=math.inf)  # was: every voxel damped to 0, an empty result with exit 0
    with pytest.raises(ValueError, match="iter_lim must be a whole number"):
        LSMRSolver(iter_lim=2.5)  # was: cut to 2 iterations unsaid
    with pytest.raises(ValueError, match="max_cholesky_rows"):
        MinNormSolver(max_cholesky_rows=100.5)
    for name in ("atol", "btol", "rcond", "max_cholesky_bytes"):  # rcond=nan: an empty result; bytes=nan: no limit
        with pytest.raises(ValueError, match=f"{name} must be a finite number"):
            MinNormSolver(**{name: math.nan})
    with pytest.raises(ValueError, match="tikhonov must be a finite number >= 0 .*got 'abc'"):
        MinNormSolver(tikhonov="abc")  # was: "'<=' not supported between instances of 'int' and 'str'"
    for name in ("atol", "btol"):  # was: btol=2 stopped lsmr at its first iterate, a shape far off its dips, exit 0
        with pytest.raises(ValueError, match=f"{name} must be below 1 .*got 2"):
            LSMRSolver(**{name: 2})
    with pytest.raises(ValueError, match="threshold"):
        MinNormSolver(threshold="mean")


def test_operator_choice_is_honoured_and_reported():
    """splat / rotate_sum / grid_sample are one matrix (Cholesky on it); an explicitly chosen
    fourier operator runs matrix-free (LSMR on it) and gives a different result; an
    auto-chosen fourier says it factorised the splat matrix; Cholesky on an explicit fourier is
    refused with a message naming the option."""
    grid = Grid(24, ndim=2)
    dirs = directions_2d(angles_2d(8))
    centre, radius = np.array([3.0, -2.0]), 30.0
    results = {}
    for backend in ("splat", "rotate_sum", "grid_sample", "fourier"):
        op = make_operator(grid, dirs, backend=backend)
        results[backend] = MinNormSolver(progress=False).solve(analytic_disk(op, centre, radius), op)
    assert [results[b].info["operator"] for b in results] == ["splat", "rotate_sum", "rotate_sum", "fourier"]
    assert [results[b].info["method"] for b in results] == ["cholesky", "cholesky", "cholesky", "lsmr"]
    np.testing.assert_allclose(results["rotate_sum"].occupancy, results["splat"].occupancy, atol=1e-5)
    assert float((results["fourier"].occupancy - results["splat"].occupancy).abs().max()) > 1e-3
    assert "no explicit matrix" in results["fourier"].info["operator_reason"]

    fourier = make_operator(grid, dirs, backend="fourier")
    fourier.auto_selected = True  # as operator=auto would leave it
    auto = MinNormSolver(progress=False).solve(analytic_disk(fourier, centre, radius), fourier)
    assert auto.info["method"] == "cholesky" and auto.info["operator"] == "splat"
    assert "chosen by operator=auto" in auto.info["operator_reason"]
    with pytest.raises(ValueError, match="operator=fourier does not have"):
        MinNormSolver(method="cholesky", progress=False).solve(analytic_disk(fourier, centre, radius),
                                                             make_operator(grid, dirs, backend="fourier"))


def test_grid_sample_is_the_reference_operator():
    grid = Grid(16, ndim=3)
    op = make_operator(grid, fibonacci_hemisphere(5), backend="grid_sample")
    assert type(op).__name__ == "RotateSumOperator" and not op.auto_selected
    with pytest.raises(ValueError, match="alias"):
        make_operator(grid, fibonacci_hemisphere(5), backend="nope")
