"""Posterior uncertainty of a reconstruction (dipnet.evaluation.uncertainty): larger along the missing cone,
calibrated against the truth, maps on the reconstruction's grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import Reach, fibonacci_hemisphere
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.ensemble import profile_noise_std
from dipnet.evaluation.uncertainty import (
    calibration_by_decile,
    fit_posterior,
    misfit_variance,
    resample,
    support,
    sure_error_rate,
    uncertainty,
    voxel_maps,
)
from dipnet.operators import make_operator
from dipnet.shapes.procedural import generated_occupancy
from dipnet.solvers.minnorm import MinNormSolver

from planning_fixtures import box_problem as make_box_problem


@pytest.fixture(scope="module")
def box_problem():
    return make_box_problem()


def test_uncertainty_is_higher_along_the_missing_cone(box_problem):
    grid, truth, dips = box_problem
    exact = Reconstruction(occupancy=torch.from_numpy(truth).float(), grid=grid)
    cap_dips = dips(Reach(tilt_range_deg=(0, 35)).uniform(12))
    cap = fit_posterior(exact, cap_dips, resolution=20)
    # the cap plan leaves the profiles along tilted directions undetermined: the predicted slab
    # variance grows with the tilt beyond the cap
    variance = [cap.profile_samples(Reach(tilt_range_deg=band).candidates()).var(axis=0).sum(axis=1).mean()
                for band in ((0, 30), (40, 50), (60, 90))]
    assert variance[0] < variance[1] < variance[2] and variance[2] > 1.3 * variance[0], variance
    # per voxel (on a coarse posterior grid, where a few dips can pin voxels down), the object is
    # more uncertain after the cap plan than after as many dips over the hemisphere, and less
    # uncertain after more dips
    where = support(exact.binary)
    std = {name: resample(torch.from_numpy(fit_posterior(exact, dips(d), resolution=10, band_voxels=0.75).std()),
                           grid.shape, mode="trilinear")[where].mean()
           for name, d in (("cap", Reach(tilt_range_deg=(0, 35)).uniform(12)), ("full", fibonacci_hemisphere(12)),
                           ("full48", fibonacci_hemisphere(48)))}
    assert std["cap"] > 1.03 * std["full"] and std["full48"] < 0.97 * std["full"], std


def test_uncertainty_is_calibrated(box_problem):
    grid, truth, dips = box_problem
    measurement = dips(fibonacci_hemisphere(16))
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    maps, summary = uncertainty(recon, measurement, operator, resolution=20)
    rates = calibration_by_decile(maps["p_wrong"], recon.binary, truth > 0.5)
    assert (recon.binary != (truth > 0.5)).any()
    # error rate rises with the uncertainty decile: rank correlation and a clear top/bottom gap
    rank = np.corrcoef(np.arange(10), np.argsort(np.argsort(rates)))[0, 1]
    assert rank > 0.7, rates
    assert rates[-1] > 3 * rates[:5].mean() + 0.01, rates
    assert 0 < summary["uncertainty_mean"] < 0.5 and 0 < summary["uncertain_fraction"] < 1


def test_maps_have_the_reconstruction_grid(box_problem):
    grid, truth, dips = box_problem
    measurement = dips(fibonacci_hemisphere(6))
    recon = Reconstruction(occupancy=torch.from_numpy(truth).float(), grid=grid)
    maps = voxel_maps(recon, fit_posterior(recon, measurement, resolution=10))
    assert maps["std"].shape == grid.shape and maps["p_wrong"].shape == grid.shape
    assert (float(maps["p_wrong"].max()) <= 0.5 + 1e-6
            and float(maps["p_wrong"][~grid.working_mask().numpy()].max()) == 0)


def test_fit_posterior_refuses_a_negative_band(box_problem):
    """The audit's case: ``band_voxels=-1`` gave the posterior of ``band_voxels=0``, no word."""
    grid, truth, dips = box_problem
    exact = Reconstruction(occupancy=torch.from_numpy(truth).float(), grid=grid)
    with pytest.raises(ValueError, match=r"band_voxels must be >= 0 .*, got -1.0"):
        fit_posterior(exact, dips(fibonacci_hemisphere(4)), resolution=10, band_voxels=-1.0)


def test_deciles_count_tied_voxels_at_their_ties_error_rate():
    """Hard votes leave most p_wrong at exactly 0. Before, a decile holding part of such a tie took the voxels in
    their order in the volume, so the same maps transposed gave other deciles. Now a tie counts at its own error
    rate: 20 voxels of p 0, 5 of them wrong (rate 1/4), ranked into 4 bins of 5 at 0.25 each, in any order."""
    rng = np.random.default_rng(0)
    binary = np.zeros((6, 6, 6), bool)
    binary[1:5, 1:5, 1:5] = True
    truth = binary.copy()
    truth[1, 1:5, 1:5] = rng.random((4, 4)) < 0.5  # some wrong calls on one face
    p_wrong = np.where(rng.random(binary.shape) < 0.3, 0.0, rng.integers(1, 4, binary.shape) / 4)
    for axes in ((0, 1, 2), (2, 1, 0), (1, 2, 0)):
        rates = calibration_by_decile(p_wrong.transpose(axes), binary.transpose(axes), truth.transpose(axes))
        if axes == (0, 1, 2):
            first = rates
        np.testing.assert_allclose(rates, first, atol=1e-12)
    p = np.zeros(20)
    wrong = np.zeros(20, bool)
    wrong[[0, 7, 8, 9, 19]] = True
    where = np.ones((20, 1, 1), bool)  # every voxel in the support
    np.testing.assert_allclose(calibration_by_decile(p[:, None, None], where, where ^ wrong[:, None, None], 4),
                               [0.25] * 4)


def test_sure_error_rate_counts_the_wrong_calls_among_the_sure_voxels():
    """Over the support and the true object, the voxels with p_wrong < 0.05: 4 of them, 1 wrong; a wrong voxel the
    map doubts (p_wrong 0.3) does not count, and a map sure of nothing gives NaN."""
    binary = np.zeros((8, 8, 8), bool)
    binary[3:5, 3:5, 3:5] = True
    truth = binary.copy()
    truth[3, 3, 3] = False  # wrong, sure
    truth[4, 4, 4] = False  # wrong, doubted
    p_wrong = np.full(binary.shape, 0.3)
    p_wrong[3, 3, 3] = p_wrong[3, 4, 3] = p_wrong[4, 3, 3] = 0.01
    p_wrong[7, 7, 7] = 0.0  # outside the support and the true object: not scored
    p_wrong[1, 4, 4] = 0.0  # in the support (two voxels off the object)
    assert sure_error_rate(p_wrong, binary, truth) == (0.25, 4, 1)
    rate, n_sure, n_wrong = sure_error_rate(np.full(binary.shape, 0.3), binary, truth)
    assert np.isnan(rate) and n_sure == n_wrong == 0


def test_a_stated_sigma_on_thinner_slabs_than_the_operators_is_summed_onto_its_slabs():
    """Dips measured on slabs half as thick as the operator's: each operator slab sums two measured ones, so its
    stated noise variance is twice theirs. It was taken as theirs, which halved the ensemble's perturbation
    variance (std 35 for a stated 50 mm^3 per measured slab)."""
    grid, sigma = Grid(16, 3), 50.0
    fine = make_operator(grid, fibonacci_hemisphere(6), 32)
    operator = make_operator(grid, fibonacci_hemisphere(6), 16)
    truth = torch.from_numpy(generated_occupancy(4, grid)).double()
    measurement = DipMeasurement(fine.directions, fine(truth), fine.slab_thickness, fine.slab_edges()[:1].expand(6),
                                 sigma=torch.full((6, 32), sigma))
    exact = Reconstruction(occupancy=truth.float(), grid=grid)
    assert misfit_variance(exact, measurement, operator) == pytest.approx(2 * sigma**2)
    assert profile_noise_std(exact, measurement, operator) == pytest.approx(sigma)
