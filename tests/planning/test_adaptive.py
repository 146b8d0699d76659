"""The adaptive loop (dipnet.planning.adaptive): it stops at the budget or when certain enough, fits one posterior
per step and plans with it; bad settings are user errors."""

from __future__ import annotations

import json
import re
import warnings

import numpy as np
import pytest
import torch

from dipnet.core.orientations import Reach
from dipnet.jobs.pipeline import run
from dipnet.operators import make_operator
from dipnet.planning.planner import NextBestDipPlanner
from dipnet.solvers.minnorm import MinNormSolver

from planning_fixtures import box_problem as make_box_problem
from planning_fixtures import reconstruct_cfg


@pytest.fixture(scope="module")
def box_problem():
    return make_box_problem()


@pytest.mark.parametrize("solver", ["lsqr", "lsmr"])
def test_the_min_norm_warning_names_the_solver_the_job_uses(solver):
    """``planner=adaptive solver=lsqr`` warned "planner=adaptive with solver=minnorm", a solver the job did not use."""
    from dipnet.planning.adaptive import warn_linear_loop_solver
    from dipnet.solvers.minnorm import LSMRSolver, LSQRSolver
    with pytest.warns(UserWarning, match=f"planner=adaptive with solver={solver}: .*for {solver} \\(a min-norm"):
        warn_linear_loop_solver({"lsqr": LSQRSolver, "lsmr": LSMRSolver}[solver]())


def test_adaptive_loop_stops_at_the_budget(tmp_path):
    with pytest.warns(UserWarning, match="solver=minnorm: the planner's noise level"):  # the config's default solver
        result = run(reconstruct_cfg("resolution=16", "planner=adaptive", "planner.budget=11", "planner.batch_size=3",
                                     "planner.initial_dips=4", "planner.planner.resolution=16", "output.figures=false"),
                     tmp_path)
    planning = json.loads((tmp_path / "planning.json").read_text())
    assert result.measurement.n_orientations == 11 and planning["stop_reason"] == "budget"
    assert [h["n_dips"] for h in planning["history"]] == [4, 7, 10, 11]
    # the rows' uncertainty figures come from the planner's own posterior, which the report states (the
    # job's metrics.json from output.uncertainty: with another seed or method the two differ)
    assert planning["posterior"] == {"method": "linearised", "resolution": 16, "n_samples": 64, "band_voxels": 1.5,
                                     "floor": 0.05, "seed": 0, "max_rows": 4000, "max_work": 6e7}
    assert [(h["posterior_resolution"], h["posterior_slabs"]) for h in planning["history"]] == [(16, 16)] * 4
    with np.load(tmp_path / "reconstruction.npz") as saved:
        assert saved["uncertainty_std"].shape == (16, 16, 16)
    assert 0 < result.metrics["uncertainty_mean"] < 0.5 \
        and len(result.metrics["error_rate_by_uncertainty_decile"]) == 10


def test_adaptive_loop_stops_when_certain_enough(tmp_path):
    run(reconstruct_cfg("resolution=16", "planner=adaptive", "planner.budget=20", "planner.initial_dips=5",
                        "planner.stop_uncertainty=0.999", "output.figures=false", "output.uncertainty=false"), tmp_path)
    planning = json.loads((tmp_path / "planning.json").read_text())
    assert planning["stop_reason"] == "uncertainty" and [h["n_dips"] for h in planning["history"]] == [5]


def _loop_callbacks(grid, dips):
    """``(dipped, acquire, reconstruct)`` for :func:`adaptive_loop` on ``box_problem``: ``acquire`` records each
    batch of directions in ``dipped`` and returns the dips of all so far, ``reconstruct`` solves them by minnorm."""
    dipped = []

    def acquire(directions):
        dipped.append(torch.as_tensor(directions))
        return dips(torch.cat(dipped))

    def reconstruct(measurement):
        operator = make_operator(grid, measurement.directions, grid.n)
        return MinNormSolver(progress=False).solve(measurement, operator), operator

    return dipped, acquire, reconstruct

def test_the_loop_fits_one_posterior_per_step_and_plans_with_it(box_problem):
    from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop

    grid, _, dips = box_problem
    dipped, acquire, reconstruct = _loop_callbacks(grid, dips)

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
    result = adaptive_loop(acquire, reconstruct, planner, Reach(),
                           AdaptiveSettings(budget=8, batch_size=2, initial_dips=4))
    assert [h["n_dips"] for h in result.history] == [4, 6, 8]
    assert planner.fitted == 3 and len(planner.given) == 2 and all(p is not None for p in planner.given)
    # planning with the loop's posterior is planning with the planner's own fit (seeded: the same)
    recon, operator = reconstruct(result.measurement)
    candidates = Reach().candidates()
    shared = planner.next(result.measurement, recon, candidates, 2, operator,
                          posterior=planner.posterior(recon, result.measurement, operator))
    assert torch.equal(shared,
                       NextBestDipPlanner(resolution=10).next(result.measurement, recon, candidates, 2, operator))


def test_a_loop_whose_initial_dips_fill_the_budget_says_it_plans_nothing():
    """The audit's case: ``planner=adaptive planner.budget=12 planner.initial_dips=12`` ran a fixed plan of 12 even dips
    under the adaptive planner's name, exit 0, without a word. A budget above the initial dips is quiet."""
    from dipnet.planning.adaptive import AdaptiveSettings

    with pytest.warns(UserWarning, match=r"planner=adaptive with initial_dips = budget = 12: every dip is spread "
                                         r"evenly .*none is planned from the data .*lower planner.initial_dips"):
        AdaptiveSettings(budget=12, initial_dips=12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        AdaptiveSettings(budget=13, initial_dips=12)


def test_bad_loop_settings_are_user_errors(tmp_path):
    from dipnet.planning.adaptive import AdaptiveSettings

    with pytest.raises(ValueError, match="initial_dips <= budget"):
        AdaptiveSettings(budget=4, initial_dips=8)
    # a percentage for the fraction (before: planner.stop_uncertainty=5 stopped at the 8 initial dips of 41, exit 0)
    with pytest.raises(ValueError, match=r"fraction in \(0, 1\) .* got 5 \(5 would stop after the first 8 dips, "
                                         r"whatever the budget; for 5 % give 0.05\)"):
        AdaptiveSettings(stop_uncertainty=5)
    with pytest.raises(ValueError, match="fraction in"):
        AdaptiveSettings(stop_uncertainty=0)
    with pytest.raises(ValueError, match="plans 3D dips"):
        run(reconstruct_cfg("ndim=2", "planner=adaptive"), tmp_path)


@pytest.mark.parametrize("stop", ["abc", True, "0.05"])
def test_a_stop_uncertainty_that_is_not_a_number_is_named(stop):
    """Before: ``planner.stop_uncertainty=abc`` failed as "could not convert string to float: 'abc'" (naming no
    option), ``true`` was read as 1 ("got 1 ... for 1 % give 0.01") and the text "0.05" as 0.05."""
    from dipnet.planning.adaptive import AdaptiveSettings
    from dipnet.planning.plans import AdaptivePlan

    message = r"stop_uncertainty must be a fraction in \(0, 1\) or null \(.*\), got " + re.escape(repr(stop)) + "$"
    with pytest.raises(ValueError, match=message):
        AdaptivePlan(stop_uncertainty=stop)
    with pytest.raises(ValueError, match=message):
        AdaptiveSettings(stop_uncertainty=stop)
    assert AdaptivePlan(stop_uncertainty=np.float32(0.5)).settings.stop_uncertainty == 0.5


def test_the_loop_never_dips_a_measured_direction_again(box_problem):
    """The audit's case: a reach of 8 candidates (tilt 0-10 deg, step 10) and a budget of 20 in batches of 6. The
    loop dipped 20 times, 5 of them along a direction it had dipped already (minutes of robot time each for planes
    measured already), and 1 candidate never, no word. Now the loop plans only unmeasured candidates, warns
    when fewer are left than a batch, and stops when none is left."""
    from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop

    grid, _, dips = box_problem
    dipped, acquire, reconstruct = _loop_callbacks(grid, dips)

    reach = Reach(tilt_range_deg=(0, 10), step_deg=10)
    with pytest.warns(UserWarning) as caught:
        result = adaptive_loop(acquire, reconstruct, NextBestDipPlanner(resolution=10), reach,
                               AdaptiveSettings(budget=20, batch_size=6, initial_dips=8))
    directions = result.measurement.directions.numpy()
    cosines = np.abs(directions @ directions.T)[np.triu_indices(len(directions), 1)]
    assert cosines.max() < np.cos(np.radians(0.5))  # no direction twice
    assert [h["n_dips"] for h in result.history] == [8, 14, 16] and result.stop_reason == "candidates"
    messages = [str(w.message) for w in caught]
    assert ("planner=adaptive: after 14 dips only 2 of the reach's 8 candidate directions are not measured yet "
            "(within 0.5 deg), fewer than the 6 of the next batch: the loop plans those 2, short of the budget of 20"
            ) in messages[0]
    assert "after 16 dips only 0 of the reach's 8 candidate directions" in messages[1]
    assert "the loop stops at 16 dips" in messages[1] and "a finer reach.step_deg (now 10 deg)" in messages[1]


def test_each_step_names_the_grid_its_posterior_was_fitted_on(tmp_path):
    """The audit's case: ``planner=adaptive resolution=24`` wrote ``"resolution": 32`` under ``posterior`` in
    planning.json (the option), while every step's posterior was fitted on 24^3 (never finer than the
    reconstruction), no word; with many dips it is coarser still. Each row now holds the grid and slabs used."""
    run(reconstruct_cfg("resolution=12", "planner=adaptive", "planner.budget=6", "planner.batch_size=3",
                        "planner.initial_dips=3", "solver=voxel", "solver.iterations=5", "output.figures=false",
                        "output.uncertainty=false"), tmp_path)
    planning = json.loads((tmp_path / "planning.json").read_text())
    assert planning["posterior"]["resolution"] == 32  # the option asked for
    assert [(h["posterior_resolution"], h["posterior_slabs"]) for h in planning["history"]] == [(12, 12)] * 2


def test_the_initial_dips_are_not_repeated(box_problem):
    """The audit's case: ``planner=adaptive reach.tilt_range_deg=[0,0]`` (a rig that dips only vertically) dipped its 8
    initial dips all along the vertical, 7 of them planes measured already, though the loop never plans a measured
    direction again; then it stopped, ``candidates``. Now the initial dips keep each direction once, with a warning."""
    from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop

    grid, _, dips = box_problem
    dipped, acquire, reconstruct = _loop_callbacks(grid, dips)
    with pytest.warns(UserWarning, match=r"7 of the 8 initial dips spread over the reach \(tilt 0-0 deg, spin 0-360 "
                                         r"deg\) repeat an earlier direction .* the loop starts from the other 1"):
        result = adaptive_loop(acquire, reconstruct, NextBestDipPlanner(resolution=10), Reach(tilt_range_deg=(0, 0)),
                               AdaptiveSettings(budget=16, batch_size=8, initial_dips=8))
    assert result.measurement.n_orientations == 1 and result.stop_reason == "candidates"


def test_the_loop_never_dips_a_direction_and_its_opposite(box_problem):
    """The audit's case: a reach of the horizontal ring (tilt 90 deg, step 60: 6 candidates on 3 lines), 1 initial dip
    and a budget of 6. The loop counted 4 candidates left and dipped them all, two pairs of opposite directions (the
    same planes twice). Now it counts lines: it plans the 2 left and stops, ``candidates``."""
    from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop

    grid, _, dips = box_problem
    dipped, acquire, reconstruct = _loop_callbacks(grid, dips)
    with pytest.warns(UserWarning, match="only 2 of the reach's 6 candidate directions are not measured yet"):
        result = adaptive_loop(acquire, reconstruct, NextBestDipPlanner(resolution=10),
                               Reach(tilt_range_deg=(90, 90), step_deg=60),
                               AdaptiveSettings(budget=6, batch_size=6, initial_dips=1))
    directions = result.measurement.directions.numpy()
    cosines = np.abs(directions @ directions.T)[np.triu_indices(len(directions), 1)]
    assert len(directions) == 3 and cosines.max() < np.cos(np.radians(0.5))
    assert result.stop_reason == "candidates"
