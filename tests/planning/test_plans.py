"""Dip plans (config group ``planner``): the fixed plan's directions and reach, the adaptive plan's loop."""

import warnings

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.core.orientations import Reach, fibonacci_hemisphere
from dipnet.planning.plans import AdaptivePlan, FixedPlan, PlanResult

AUTHORS_RIG = Reach(tilt_range_deg=(0.0, 35.0), step_deg=5.0)


def _tilt_deg(directions: torch.Tensor) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(directions[:, 2].numpy(), -1, 1)))


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_the_planner_groups_instantiate_plans_with_the_top_level_options():
    fixed = instantiate(_cfg("n_dips=20", "orientations=random", "seed=3").planner)
    assert isinstance(fixed, FixedPlan) and (fixed.n_dips, fixed.orientations, fixed.seed) == (20, "random", 3)
    adaptive = instantiate(_cfg("planner=adaptive", "planner.budget=11", "planner.planner.resolution=16").planner)
    assert isinstance(adaptive, AdaptivePlan) and adaptive.settings.budget == 11
    assert adaptive.planner.options["resolution"] == 16


def test_a_fixed_plan_inside_the_reach_is_the_orientation_set():
    directions = FixedPlan("fibonacci", 30).directions(3, Reach())
    assert torch.allclose(directions, fibonacci_hemisphere(30))


def test_a_fibonacci_plan_leaving_the_reach_becomes_uniform_over_it():
    directions = FixedPlan("fibonacci", 20).directions(3, AUTHORS_RIG)
    assert directions.shape == (20, 3) and _tilt_deg(directions).max() <= 35 + 1e-9
    assert torch.allclose(directions.norm(dim=1), torch.ones(20, dtype=directions.dtype))


def test_a_random_plan_leaving_the_reach_is_refused():
    with pytest.raises(ValueError, match="leaves the reach"):
        FixedPlan("random", 20, seed=1).directions(3, AUTHORS_RIG)


@pytest.mark.parametrize("option, message", [
    ({"n_dips": 8.5}, r"n_dips must be a whole number, got 8.5"),
    ({"n_dips": True}, r"n_dips must be a whole number, got True"),
    ({"n_dips": 0}, r"n_dips must be a whole number >= 1, got 0"),
    ({"seed": 1.5}, r"seed must be a whole number, got 1.5"),
    ({"seed": -1}, r"seed must be a whole number >= 0, got -1"),
])
def test_a_fixed_plan_count_or_seed_that_is_not_whole_is_named(option, message):
    """Before: ``planner.n_dips=8.5`` planned 8 dips and ``planner.seed=1.5`` used seed 1, exit 0 (the top-level
    ``n_dips`` and ``seed`` were checked, the planner's own keys were not)."""
    with pytest.raises(ValueError, match=message):
        FixedPlan("random", **{"n_dips": 4, "seed": 0, **option})
    assert FixedPlan("random", 4.0, seed=2.0).directions(3).shape == (4, 3)


def test_2d_plans_ignore_the_reach():
    directions = FixedPlan("uniform", 6).directions(2, AUTHORS_RIG)
    angles = np.degrees(np.arctan2(directions[:, 1].numpy(), directions[:, 0].numpy())) % 180
    assert np.allclose(np.sort(angles) - np.sort(angles)[0], np.arange(6) * 30.0, atol=1e-9)


def test_a_fixed_plan_dips_once_and_has_no_report():
    calls = []
    result = FixedPlan("fibonacci", 12).run(lambda d: calls.append(d) or "measured", 3, None)
    assert isinstance(result, PlanResult) and result.measurement == "measured" and result.report is None
    assert len(calls) == 1 and calls[0].shape == (12, 3)


def test_the_adaptive_plan_needs_3d_and_a_solver():
    plan = AdaptivePlan(budget=4, initial_dips=2)
    with pytest.raises(ValueError, match="plans 3D dips"):
        plan.run(lambda d: None, 2, None)
    with pytest.raises(ValueError, match="give solver and make_operator"):
        plan.run(lambda d: None, 3, None)
    with pytest.raises(ValueError, match="initial_dips <= budget"):
        AdaptivePlan(budget=4, initial_dips=8)


def test_a_fixed_plan_over_a_reach_too_narrow_for_its_dips_says_they_repeat():
    """The audit's case: ``reach.tilt_range_deg=[0,0] n_dips=41`` dipped 41 times along the vertical, no word."""
    with pytest.warns(UserWarning, match=r"n_dips=41 over the reach \(tilt 0-0 deg, spin 0-360 deg\): 40 of the dips "
                                         r"repeat an earlier direction \(within 0.5 deg\) "
                                         r".* 1 distinct direction\(s\) in all"):
        directions = FixedPlan("fibonacci", 41).directions(3, Reach(tilt_range_deg=(0, 0)))
    assert directions.shape == (41, 3)  # the plan asked for is kept
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        FixedPlan("fibonacci", 41).directions(3, AUTHORS_RIG)  # distinct directions: no word


@pytest.mark.parametrize("option", ["budget", "batch_size", "initial_dips"])
def test_a_count_of_the_loop_that_is_not_whole_is_refused(option):
    """The audit's case: ``planner=adaptive planner.budget=40.7`` dipped 40 times, no word (``int()`` cut it)."""
    with pytest.raises(ValueError, match=rf"{option} must be a whole number, got 7.5 \(2.5 is not cut to 2\)"):
        AdaptivePlan(**{option: 7.5})
    assert AdaptivePlan(budget=40.0).settings.budget == 40  # a whole float is the number


@pytest.mark.parametrize("options,opening", [
    ({"initial_dips": 0}, "initial_dips: "), ({"initial_dips": 50, "budget": 12}, "initial_dips: "),
    ({"batch_size": 0}, "batch_size: "),
])
def test_a_count_of_the_loop_out_of_range_opens_with_the_option(options, opening):
    """planner.initial_dips=0 said "need 1 <= initial_dips <= budget ...", which a job's error could not name by
    its path (planner.initial_dips): the message opens with the option at fault."""
    with pytest.raises(ValueError, match=rf"^{opening}need 1 <= initial_dips <= budget and batch_size >= 1, got "):
        AdaptivePlan(**options)


def test_the_adaptive_loop_solves_without_the_surface_refit_and_the_job_refits_its_own_result(tmp_path, monkeypatch):
    """The loop reads each batch's occupancy only: before, every batch's solve refitted its surface too (about 40 s
    each for solver=voxel_learned at 64^3), for a mesh nobody read."""
    from dipnet.jobs.pipeline import run
    from dipnet.solvers.surface_refit import SurfaceRefit

    refits, refit = [], SurfaceRefit.refit
    monkeypatch.setattr(SurfaceRefit, "refit", lambda self, recon, *args, **kw: refits.append(
        recon.info["solver"]) or refit(self, recon, *args, **kw))
    result = run(_cfg("resolution=16", "planner=adaptive", "planner.budget=16", "planner.initial_dips=8",
                      "planner.planner.resolution=16", "solver=voxel", "solver.iterations=30",
                      "solver.surface_refit={steps: 5, probe_steps: 5}", "output.progress=false",
                      "output.figures=false", "output.uncertainty=false", "output.resolvability=false"), tmp_path)
    assert result.measurement.n_orientations == 16
    assert len(refits) == 1 and result.reconstruction.info["surface_refit"]["reason"]  # the job's own solve alone
