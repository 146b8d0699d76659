"""Scan planning: reachable candidates, the linearised uncertainty, next-best-dip, the closed loop."""

import json

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from dipnet.core.grid import Grid
from dipnet.operators import make_operator
from dipnet.core.orientations import Reach, fibonacci_hemisphere, reachable_candidates
from dipnet.simulator.physics import LevelSensor
from dipnet.jobs.pipeline import run
from dipnet.planning.planner import NextBestDipPlanner
from dipnet.core.reconstruction import Reconstruction
from dipnet.shapes import builtin_shape
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.evaluation.uncertainty import (calibration_by_decile, fit_posterior, resample, support, uncertainty,
                                           voxel_maps)


def _tilt_spin(directions):
    d = torch.as_tensor(directions).numpy()
    return np.degrees(np.arccos(np.clip(d[:, 2], -1, 1))), np.mod(np.degrees(np.arctan2(-d[:, 1], d[:, 0])), 360)


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=["output.progress=false", *overrides])


@pytest.fixture(scope="module")
def box_problem():
    """A chamber box at 20^3, its true occupancy and dips simulated along a plan (30 dB)."""
    grid = Grid(20, 3)
    shape = builtin_shape("chamber_box", 3, 0.9 * grid.radius)
    truth = shape.occupancy(grid, supersample=2).numpy()

    def dips(directions):
        _, measurement = simulate_measurement(shape, directions, grid=grid, sensor=LevelSensor(snr_db=30, seed=1),
                                              progress=False)
        return measurement

    return grid, truth, dips


# ---------------------------------------------------------------------------- reach
def test_candidates_stay_within_the_rig_limits_and_cover_them():
    reach = Reach(tilt_range_deg=(10, 35), spin_range_deg=(0, 90), step_deg=5)
    tilt, spin = _tilt_spin(reach.candidates())
    assert tilt.min() >= 10 - 1e-9 and tilt.max() <= 35 + 1e-9
    assert spin.min() >= -1e-9 and spin.max() <= 90 + 1e-9
    # every reachable direction lies within about one step of a candidate
    rng = np.random.default_rng(0)
    t, s = rng.uniform(10, 35, 500), rng.uniform(0, 90, 500)
    from dipnet.core.orientations import rig_to_direction
    probes = rig_to_direction(t, s).numpy()
    nearest = np.degrees(np.arccos(np.clip(probes @ reach.candidates().numpy().T, -1, 1))).min(axis=1)
    assert nearest.max() < 5.0
    assert bool(reach.contains(reach.uniform(30)).all())
    assert not bool(reach.contains(fibonacci_hemisphere(30)).all())


def test_presets_and_bad_limits():
    authors = _cfg("reach=authors_rig").reach
    assert list(authors.tilt_range_deg) == [0.0, 35.0]
    assert len(reachable_candidates()) > len(reachable_candidates((0, 35)))
    with pytest.raises(ValueError, match="tilt range"):
        Reach(tilt_range_deg=(0, 120))
    with pytest.raises(ValueError, match="step"):
        Reach(step_deg=0)


def test_fixed_plan_under_the_authors_rig_stays_in_the_cap(tmp_path):
    result = run(_cfg("resolution=16", "n_dips=12", "reach=authors_rig", "output.figures=false",
                      "output.uncertainty=false"), tmp_path)
    tilt, _ = _tilt_spin(result.measurement.directions)
    assert result.measurement.n_orientations == 12 and tilt.max() <= 35 + 1e-9


# ---------------------------------------------------------------------------- uncertainty
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
    assert float(maps["p_wrong"].max()) <= 0.5 + 1e-6 and float(maps["p_wrong"][~grid.working_mask().numpy()].max()) == 0


# ---------------------------------------------------------------------------- planner
def test_planner_fills_the_missing_cone(box_problem):
    grid, truth, dips = box_problem
    measurement = dips(Reach(tilt_range_deg=(0, 35)).uniform(12))
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    planner = NextBestDipPlanner(resolution=20)
    chosen = planner.next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    tilt, spin = _tilt_spin(chosen)
    assert tilt.min() > 45, tilt
    # the batch is diverse: no two picks measure (nearly) the same planes
    cosines = np.abs(chosen.numpy() @ chosen.numpy().T)[np.triu_indices(4, 1)]
    assert cosines.max() < np.cos(np.radians(15))
    # deterministic: the same dips give the same plan
    again = NextBestDipPlanner(resolution=20).next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    assert torch.equal(again, chosen)
    assert planner.last_seconds < 10


# ---------------------------------------------------------------------------- closed loop
def test_adaptive_loop_stops_at_the_budget(tmp_path):
    with pytest.warns(UserWarning, match="solver=minnorm: the planner's noise level"):  # the config's default solver
        result = run(_cfg("resolution=16", "planner=adaptive", "planner.budget=11", "planner.batch_size=3",
                          "planner.initial_dips=4", "planner.planner.resolution=16", "output.figures=false"), tmp_path)
    planning = json.loads((tmp_path / "planning.json").read_text())
    assert result.measurement.n_orientations == 11 and planning["stop_reason"] == "budget"
    assert [h["n_dips"] for h in planning["history"]] == [4, 7, 10, 11]
    with np.load(tmp_path / "reconstruction.npz") as saved:
        assert saved["uncertainty_std"].shape == (16, 16, 16)
    assert 0 < result.metrics["uncertainty_mean"] < 0.5 and len(result.metrics["error_rate_by_uncertainty_decile"]) == 10


def test_adaptive_loop_stops_when_certain_enough(tmp_path):
    run(_cfg("resolution=16", "planner=adaptive", "planner.budget=20", "planner.initial_dips=5",
             "planner.stop_uncertainty=100", "output.figures=false", "output.uncertainty=false"), tmp_path)
    planning = json.loads((tmp_path / "planning.json").read_text())
    assert planning["stop_reason"] == "uncertainty" and [h["n_dips"] for h in planning["history"]] == [5]


def test_the_loop_fits_one_posterior_per_step_and_plans_with_it(box_problem):
    from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop

    grid, _, dips = box_problem
    dipped = []

    def acquire(directions):
        dipped.append(torch.as_tensor(directions))
        return dips(torch.cat(dipped))

    def reconstruct(measurement):
        operator = make_operator(grid, measurement.directions, grid.n)
        return MinNormSolver(progress=False).solve(measurement, operator), operator

    class Counting(NextBestDipPlanner):
        def __init__(self):
            super().__init__(resolution=10)
            self.fitted, self.given = 0, []

        def posterior(self, *args, **kwargs):
            self.fitted += 1
            return super().posterior(*args, **kwargs)

        def next(self, *args, posterior=None, **kwargs):
            self.given.append(posterior)
            return super().next(*args, posterior=posterior, **kwargs)

    planner = Counting()
    result = adaptive_loop(acquire, reconstruct, planner, Reach(), AdaptiveSettings(budget=8, batch_size=2, initial_dips=4))
    assert [h["n_dips"] for h in result.history] == [4, 6, 8]
    assert planner.fitted == 3 and len(planner.given) == 2 and all(p is not None for p in planner.given)
    # planning with the loop's posterior is planning with the planner's own fit (seeded: the same)
    recon, operator = reconstruct(result.measurement)
    candidates = Reach().candidates()
    shared = planner.next(result.measurement, recon, candidates, 2, operator,
                          posterior=planner.posterior(recon, result.measurement, operator))
    assert torch.equal(shared, NextBestDipPlanner(resolution=10).next(result.measurement, recon, candidates, 2, operator))


def test_bad_loop_settings_are_user_errors(tmp_path):
    from dipnet.planning.adaptive import AdaptiveSettings

    with pytest.raises(ValueError, match="initial_dips <= budget"):
        AdaptiveSettings(budget=4, initial_dips=8)
    with pytest.raises(ValueError, match="plans 3D dips"):
        run(_cfg("ndim=2", "planner=adaptive"), tmp_path)
