"""The uncertainty maps of a run, into the run directory (dipnet.outputs.uncertainty): added to
reconstruction.npz beside the occupancy, a figure, and the summary with the error rate per decile."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.evaluation.uncertainty import support, uncertainty
from dipnet.outputs.uncertainty import write_uncertainty
from dipnet.shapes import Ball
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.minnorm import MinNormSolver


@pytest.fixture(scope="module")
def solved():
    """A ball at 12^3 from 6 noisy dips (too few: the binary call has errors), its min-norm reconstruction."""
    grid = Grid(12, 3, 100.0)
    shape = Ball(30.0)
    _, measurement = simulate_measurement(shape, fibonacci_hemisphere(6), grid=grid,
                                          sensor=LevelSensor(snr_db=30, seed=1), progress=False)
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    truth = shape.occupancy(grid, supersample=2).numpy()
    return grid, measurement, operator, recon, truth


def test_the_maps_join_the_reconstruction_file_and_the_figure_is_drawn(solved, tmp_path):
    grid, measurement, operator, recon, truth = solved
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # whether 6 dips give a calibrated map is not the point here
        scores = write_uncertainty(tmp_path, recon, measurement, operator, truth=truth)
    with np.load(tmp_path / "reconstruction.npz") as saved:
        assert saved["uncertainty_std"].shape == grid.shape and saved["uncertainty_p_wrong"].shape == grid.shape
        np.testing.assert_array_equal(saved["binary"], recon.binary)  # the reconstruction itself is kept
        p_wrong = saved["uncertainty_p_wrong"]
    assert 0.0 <= p_wrong.min() and p_wrong.max() <= 0.5 + 1e-6
    assert {"uncertainty_mean", "uncertain_fraction"} <= set(scores)
    deciles = scores["error_rate_by_uncertainty_decile"]
    assert len(deciles) == 10 and all(0.0 <= v <= 1.0 for v in deciles)
    assert (tmp_path / "uncertainty.png").read_bytes()[:4] == b"\x89PNG"


def test_without_a_truth_no_deciles_and_without_figure_no_png(solved, tmp_path):
    _, measurement, operator, recon, _ = solved
    scores = write_uncertainty(tmp_path, recon, measurement, operator, figure=False)
    assert "error_rate_by_uncertainty_decile" not in scores and "uncertainty_mean" in scores
    assert not (tmp_path / "uncertainty.png").exists() and (tmp_path / "reconstruction.npz").exists()


def test_a_map_that_does_not_rank_the_errors_is_reported(solved, tmp_path):
    """Judged against a 'truth' that differs from the reconstruction only in its least uncertain support voxel,
    the most uncertain decile is not worse than the least: the run says the uncertainty is not calibrated (a
    warning, the scores still written)."""
    grid, measurement, operator, recon, _ = solved
    p_wrong = uncertainty(recon, measurement, operator)[0]["p_wrong"]
    truth = recon.binary.copy()
    candidates = np.flatnonzero(support(recon.binary))
    truth.flat[candidates[np.argmin(p_wrong.flat[candidates])]] ^= True
    with pytest.warns(UserWarning, match="uncertainty is not calibrated on this run"):
        scores = write_uncertainty(tmp_path, recon, measurement, operator, truth=truth, figure=False)
    assert scores["error_rate_by_uncertainty_decile"][0] > 0 == scores["error_rate_by_uncertainty_decile"][-1]


def test_a_reconstruction_without_a_wrong_voxel_has_nothing_to_calibrate(solved, tmp_path):
    """Before: 'uncertainty is not calibrated on this run: error rate 0.000 ... vs 0.000' on a perfect run."""
    _, measurement, operator, recon, _ = solved
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        scores = write_uncertainty(tmp_path, recon, measurement, operator, truth=recon.binary, figure=False)
    assert scores["error_rate_by_uncertainty_decile"] == [0.0] * 10


def test_an_empty_reconstruction_is_not_called_uncalibrated(solved, tmp_path):
    """Before: 'uncertainty is not calibrated on this run: error rate 1.000 ... vs 1.000' on an empty result, whose
    every true voxel is a wrong call whatever the map says (the job says once that it is empty)."""
    grid, measurement, operator, recon, truth = solved
    empty = type(recon)(recon.occupancy * 0, grid, recon.threshold)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        scores = write_uncertainty(tmp_path, empty, measurement, operator, truth=truth > 0.5, figure=False)
    assert scores["error_rate_by_uncertainty_decile"] == [1.0] * 10


def test_a_map_that_is_certain_where_the_shape_is_wrong_is_reported(solved, tmp_path):
    """The audit's case: a part the reconstruction misses far from its boundary (a missing cone: 41 dips within 10 deg
    of the vertical on a generated shape, 24^3, gave 31 wrong voxels at p_wrong < 0.05, 6 % of those called sure)
    gets the prior's floor and a p_wrong near 0, yet the deciles still rose and nothing was said. Now the error rate
    of the voxels the map calls sure is scored (``error_rate_where_sure``) and a rate above 0.05 is a warning."""
    grid, measurement, operator, recon, _ = solved
    p_wrong = uncertainty(recon, measurement, operator)[0]["p_wrong"]
    sure_inside = recon.binary & (p_wrong < 0.05)
    truth = recon.binary & ~sure_inside  # wrong exactly where the map is sure: a void the dips could not see
    assert sure_inside.sum() >= 3
    with pytest.warns(UserWarning, match=r"uncertainty is confidently wrong on this run: \d+ of the \d+ voxels"):
        scores = write_uncertainty(tmp_path, recon, measurement, operator, truth=truth, figure=False)
    assert scores["error_rate_where_sure"] > 0.05


def test_a_map_right_where_it_is_sure_is_not_reported(solved, tmp_path):
    _, measurement, operator, recon, _ = solved
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        scores = write_uncertainty(tmp_path, recon, measurement, operator, truth=recon.binary, figure=False)
    assert scores["error_rate_where_sure"] == 0.0
