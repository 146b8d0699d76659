"""Uncertainty from samples: an ensemble of reconstructions of perturbed dips, and calibration scores."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.evaluation.ensemble import (RandomStart, brier_score, centred_occupancy, ensemble_maps,
                                        ensemble_uncertainty, member, occupancy_probability, reliability,
                                        sample_ensemble)
from dipnet.evaluation.uncertainty import calibration_by_decile
from dipnet.operators import make_operator
from dipnet.shapes import builtin_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.deep_image_prior import DeepImagePriorSolver
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver


@pytest.fixture(scope="module")
def box_case():
    """A chamber box at 20^3 from 16 dips at 30 dB: truth (bool), measurement, operator, voxel solver and its result."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    grid = Grid(20, 3)
    shape = builtin_shape("chamber_box", 3, 0.9 * grid.radius)
    truth = shape.occupancy(grid, supersample=2).numpy() > 0.5
    _, measurement = simulate_measurement(shape, fibonacci_hemisphere(16), grid=grid,
                                          sensor=LevelSensor(snr_db=30, seed=1), progress=False)
    operator = make_operator(grid, measurement.directions, grid.n)
    solver = VoxelSolver(iterations=200, progress=False)
    yield truth, measurement, operator, solver, solver.solve(measurement, operator)
    torch.set_num_threads(threads)


def test_probability_is_in_range_and_deterministic_by_seed(box_case):
    _, measurement, operator, solver, recon = box_case
    options = {"n_samples": 2, "iterations_scale": 0.25}
    a = sample_ensemble(solver, recon, measurement, operator, seed=3, **options)
    b = sample_ensemble(solver, recon, measurement, operator, seed=3, **options)
    c = sample_ensemble(solver, recon, measurement, operator, seed=4, **options)
    assert np.array_equal(a.occupancies, b.occupancies) and not np.array_equal(a.occupancies, c.occupancies)
    maps = ensemble_maps(recon, a)
    p = maps["probability"]
    assert p.shape == operator.grid.shape and 0 <= p.min() and p.max() <= 1 and 0 < p.mean() < 1
    assert np.all(maps["std"] >= 0) and a.noise_std > 0
    inside = recon.binary
    np.testing.assert_allclose(maps["p_wrong"][inside], 1 - p[inside], atol=1e-6)
    assert maps["p_wrong"][~operator.grid.working_mask().numpy()].max() == 0
    hard = ensemble_maps(recon, a, soft=False)["probability"]
    assert set(np.unique(hard)) <= {0.0, 0.5, 1.0}
    assert solver.progress is False and solver.seed == 0 and solver.warm_start is None  # the job's solver is unchanged


def test_a_members_occupancy_maps_its_level_to_one_half_and_keeps_empty_empty():
    """Shifting by ``1/2 - threshold`` gave an empty voxel of a member thresholded at 0.2 a probability of 0.3."""
    o = np.array([-0.1, 0.0, 0.1, 0.2, 0.6, 1.0, 1.3])
    np.testing.assert_allclose(centred_occupancy(o, 0.2), [0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(centred_occupancy(o, 0.5), np.clip(o, 0, 1), atol=1e-6)  # the level 1/2: as it was


def test_a_linear_solvers_ensemble_counts_its_members_calls(box_case):
    """The audit's case: ``minnorm``'s linear field ripples 0.1-0.2 far outside the object, which averaged as
    occupancies made the chamber box's ``expected_error_fraction`` 0.47 (24^3, 120 dips) where 0.04 of it was wrong.
    A linear solver's members now vote, and outside the working ball the probability is 0, as ``p_wrong`` is."""
    truth, measurement, operator, _, _ = box_case
    solver = MinNormSolver(progress=False)
    recon = solver.solve(measurement, operator)
    maps, summary = ensemble_uncertainty(recon, measurement, operator, solver, n_samples=4, seed=1)
    assert set(np.unique(maps["probability"])) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    assert maps["probability"][~operator.grid.working_mask().numpy()].max() == 0
    wrong = np.sum(recon.binary != truth) / np.sum(recon.binary)
    assert summary["expected_error_fraction"] < 2.5 * wrong + 0.05


def test_error_rate_rises_with_the_ensemble_uncertainty_decile(box_case):
    truth, measurement, operator, solver, recon = box_case
    maps, summary = ensemble_uncertainty(recon, measurement, operator, solver, n_samples=4)
    rates = calibration_by_decile(maps["p_wrong"], recon.binary, truth)
    assert (recon.binary != truth).any()
    rank = np.corrcoef(np.arange(10), np.argsort(np.argsort(rates)))[0, 1]
    assert rank > 0.7, rates
    assert rates[-1] > 3 * rates[:5].mean() + 0.01, rates
    assert summary["uncertainty_samples"] == 4 and 0 < summary["uncertainty_mean"] < 0.5
    # a probability, better than the reference's hard calls alone
    assert brier_score(maps["probability"], recon.binary, truth) < brier_score(recon.binary, recon.binary, truth)


def test_members_are_independent_copies():
    solver = VoxelSolver(iterations=100, progress=True)
    copy = member(solver, 2, seed=5, iterations_scale=0.5)
    assert copy is not solver and copy.seed == 8 and copy.iterations == 50 and copy.progress is False
    assert isinstance(copy.warm_start, RandomStart) and solver.warm_start is None and solver.iterations == 100
    assert member(DeepImagePriorSolver(), 0, seed=0).warm_start is None  # its seed draws its start
    assert not hasattr(member(MinNormSolver(), 0, seed=0), "warm_start")
    refitting = VoxelSolver(surface_refit={})
    # occupancies only
    assert member(refitting, 0, seed=0).surface_refit is None and refitting.surface_refit is not None
    nested = VoxelSolver(warm_start=VoxelSolver(progress=True))  # voxel_learned's plain voxel start
    assert member(nested, 0, seed=0).warm_start.progress is False and nested.warm_start.progress is True


def test_members_nested_warm_start_solvers_take_the_members_seed(box_case):
    """``voxel_learned``'s plain voxel start (``warm_start.seed: ${seed}``) kept the job's one seed in every member,
    so members differed by their perturbed data alone; each member's nested solvers (a start's start too) now take
    the member's seed, the job's solver is unchanged, and the same seed gives the same ensemble."""
    innermost = VoxelSolver(iterations=10, progress=True, seed=0)
    nested = VoxelSolver(iterations=10, progress=False, seed=0,
                         warm_start=VoxelSolver(iterations=10, progress=False, seed=0, warm_start=innermost))
    first, second = member(nested, 0, seed=5), member(nested, 1, seed=5)
    assert (first.seed, first.warm_start.seed, first.warm_start.warm_start.seed) == (6, 6, 6)
    assert (second.seed, second.warm_start.seed, second.warm_start.warm_start.seed) == (7, 7, 7)
    assert first.warm_start.warm_start.progress is False and innermost.progress is True
    assert nested.warm_start.seed == 0 and nested.warm_start.warm_start is innermost and innermost.seed == 0
    assert member(nested, 0, seed=5).warm_start.seed == first.warm_start.seed  # deterministic by seed
    _, measurement, operator, _, recon = box_case
    job = VoxelSolver(iterations=20, progress=False, warm_start=VoxelSolver(iterations=20, progress=False))
    options = {"n_samples": 2, "seed": 3}
    a = sample_ensemble(job, recon, measurement, operator, **options)
    b = sample_ensemble(job, recon, measurement, operator, **options)
    assert np.array_equal(a.occupancies, b.occupancies) and np.array_equal(a.binaries, b.binaries)


def test_members_nested_start_begins_from_its_own_random_start(box_case):
    """The voxel solver's seed draws nothing, so the innermost nested solver (the plain voxel start) starts from the
    member's :class:`RandomStart`: without perturbed data the members still differ (before: identical), the same
    seed still gives the same ensemble, and ``random_start=False`` keeps the plain start."""
    _, measurement, operator, _, recon = box_case
    job = VoxelSolver(iterations=20, progress=False, warm_start=VoxelSolver(iterations=20, progress=False))
    copy = member(job, 1, seed=5)
    assert isinstance(copy.warm_start.warm_start, RandomStart) and copy.warm_start.warm_start.seed == 7
    assert member(job, 1, seed=5, random_start=False).warm_start.warm_start is None
    assert job.warm_start.warm_start is None  # the job's solver is unchanged
    options = {"n_samples": 2, "seed": 3, "perturb": False}
    a = sample_ensemble(job, recon, measurement, operator, **options)
    assert not np.array_equal(a.occupancies[0], a.occupancies[1])
    assert np.array_equal(a.occupancies, sample_ensemble(job, recon, measurement, operator, **options).occupancies)


def test_random_start_fills_the_measured_volume_on_average(box_case):
    _, measurement, operator, _, _ = box_case
    start = RandomStart(seed=0)(measurement, operator)
    grid = operator.grid
    level = measurement.volume_estimate() / grid.extent**3 / float(grid.working_mask().double().mean())
    assert start.shape == grid.shape and 0 <= float(start.min()) and float(start.max()) <= 1
    assert float(start.mean()) == pytest.approx(level, abs=0.05) and float(start.std()) > 0.1
    assert torch.equal(start, RandomStart(seed=0)(measurement, operator))


def test_bad_ensemble_options(box_case):
    _, measurement, operator, solver, recon = box_case
    with pytest.raises(ValueError, match="n_samples >= 2"):
        sample_ensemble(solver, recon, measurement, operator, n_samples=1)
    with pytest.raises(ValueError, match="iterations_scale"):
        sample_ensemble(solver, recon, measurement, operator, iterations_scale=0.0)


def test_brier_score_and_reliability_on_known_answers():
    truth = np.zeros((12, 12), bool)
    truth[4:8, 4:8] = True
    assert brier_score(truth.astype(float), truth, truth) == 0.0
    assert brier_score(np.full(truth.shape, 0.5), truth, truth) == pytest.approx(0.25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # before: "Mean of empty slice" with an empty result and truth
        nothing = np.zeros_like(truth)
        assert np.isnan(brier_score(nothing.astype(float), nothing, nothing))
    predicted, observed, count, ece = reliability(truth.astype(float), truth, truth)
    assert ece == 0.0 and count.sum() == 52  # the 4x4 square dilated twice (4-connected): 16 + 16 + 20 voxels
    assert observed[0] == 0.0 and observed[-1] == 1.0 and np.isnan(predicted[5])
    # a probability of 0.3 everywhere: observed fraction = the occupied share of the scored voxels
    _, observed, count, ece = reliability(np.full(truth.shape, 0.3), truth, truth)
    share = truth.sum() / count.sum()
    assert observed[3] == pytest.approx(share) and ece == pytest.approx(abs(0.3 - share))
    # the linearised method's p_wrong as a probability
    np.testing.assert_allclose(occupancy_probability(np.array([0.1, 0.2]), np.array([True, False])), [0.9, 0.2])
