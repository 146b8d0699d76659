"""The next-best-dip planner (dipnet.planning.planner): its picks fill the missing cone, diverse and deterministic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.orientations import Reach
from dipnet.operators import make_operator
from dipnet.planning.planner import NextBestDipPlanner
from dipnet.solvers.minnorm import MinNormSolver

from planning_fixtures import box_problem as make_box_problem
from planning_fixtures import tilt_spin
from script_runs import one_line_error


@pytest.fixture(scope="module")
def box_problem():
    return make_box_problem()


def test_planner_fills_the_missing_cone(box_problem):
    grid, truth, dips = box_problem
    measurement = dips(Reach(tilt_range_deg=(0, 35)).uniform(12))
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    planner = NextBestDipPlanner(resolution=20)
    chosen = planner.next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    tilt, spin = tilt_spin(chosen)
    assert tilt.min() > 45, tilt
    # the batch is diverse: no two picks measure (nearly) the same planes
    cosines = np.abs(chosen.numpy() @ chosen.numpy().T)[np.triu_indices(4, 1)]
    assert cosines.max() < np.cos(np.radians(15))
    # deterministic: the same dips give the same plan
    again = NextBestDipPlanner(resolution=20).next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    assert torch.equal(again, chosen)
    assert planner.last_seconds < 10


@pytest.mark.parametrize("band", [-1.0, float("nan"), float("inf")])
def test_a_negative_boundary_band_is_refused(band):
    """The audit's case: ``band_voxels=-1`` was taken as 0 (scipy's blur of a negative sigma), no word."""
    with pytest.raises(ValueError, match=r"band_voxels must be >= 0 \(the width of the uncertain boundary band"):
        NextBestDipPlanner(band_voxels=band)
    NextBestDipPlanner(band_voxels=0.0)  # no band: allowed


def test_reconstruct_refuses_a_negative_band_before_any_dip(tmp_path, script_run):
    done = script_run("reconstruct", tmp_path, "planner=adaptive", "planner.planner.band_voxels=-1", "resolution=16")
    assert one_line_error(done) == ("error: planner.planner.band_voxels must be >= 0 (the width of the uncertain "
                                    "boundary band, in posterior-grid voxels; 0: no band), got -1.0")


def test_the_planner_never_picks_a_measured_direction(box_problem):
    """A candidate along a measured dip's line (or its opposite: the same planes) is not planned again; asking for
    more new dips than unmeasured candidates is refused, naming both counts."""
    from dipnet.planning.planner import measured_candidates

    grid, _, dips = box_problem
    candidates = Reach(tilt_range_deg=(0, 10), step_deg=10).candidates()  # 8 directions
    measurement = dips(torch.cat([candidates[:5], Reach().uniform(4)]))
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    assert measured_candidates(candidates, -2.0 * measurement.directions).tolist() == [True] * 5 + [False] * 3
    chosen = NextBestDipPlanner(resolution=10).next(measurement, recon, candidates, k=3, operator=operator)
    assert sorted(map(tuple, chosen.tolist())) == sorted(map(tuple, candidates[5:].tolist()))
    with pytest.raises(ValueError, match=r"asked for 4 new dips, but only 3 of the 8 candidates are not measured"):
        NextBestDipPlanner(resolution=10).next(measurement, recon, candidates, k=4, operator=operator)


def test_the_posterior_grid_and_samples_must_be_whole_numbers():
    """``planner.planner.resolution=24.5`` was cut to 24 unsaid."""
    with pytest.raises(ValueError, match=r"resolution must be a whole number, got 24.5"):
        NextBestDipPlanner(resolution=24.5)
    with pytest.raises(ValueError, match=r"n_samples must be a whole number"):
        NextBestDipPlanner(n_samples="64")


@pytest.mark.parametrize("option, message", [
    ({"floor": True}, r"floor must be a number, got True"),
    ({"band_voxels": True}, r"band_voxels must be a number, got True"),
    ({"band_voxels": "abc"}, r"band_voxels must be a number, got 'abc'"),
    ({"seed": 1.5}, r"seed must be a whole number, got 1.5"),
    ({"seed": True}, r"seed must be a whole number, got True"),
    ({"seed": -1}, r"seed must be a whole number >= 0, got -1"),
])
def test_a_planner_option_of_the_wrong_type_is_named(option, message):
    """Before: ``planner.planner.floor=true`` and ``band_voxels=true`` were read as 1, ``seed=1.5`` as seed 1 and
    ``seed=true`` as 1, a run with exit 0; ``band_voxels=abc`` failed as "could not convert string to float"."""
    with pytest.raises(ValueError, match=message):
        NextBestDipPlanner(**option)
    assert NextBestDipPlanner(floor=1, band_voxels=np.float64(2.0), seed=3.0).options["seed"] == 3


def test_a_batch_never_holds_a_direction_and_its_opposite_even_with_noisy_data():
    """The audit's case: with 2 dips at -10 dB the hemisphere's candidates at tilt 90 deg hold ``c`` and ``-c`` (the
    same planes); the conditioning on a pick hardly lowered its opposite's score when the noise dwarfs the predicted
    variances, and the batch of 8 held both. Asking for more dips than unmeasured lines is refused."""
    from dipnet.core.grid import Grid
    from dipnet.planning.planner import repeated_directions
    from dipnet.shapes import builtin_shape
    from dipnet.simulator.physics import LevelSensor
    from dipnet.simulator.simulate import simulate_measurement

    grid = Grid(20, 3)
    _, measurement = simulate_measurement(builtin_shape("chamber_box", 3, 0.9 * grid.radius),
                                          Reach(tilt_range_deg=(0, 35)).uniform(2), grid=grid,
                                          sensor=LevelSensor(snr_db=-10, seed=1), progress=False)
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    candidates = Reach(step_deg=20).candidates()
    for criterion in ("information", "variance"):
        chosen = NextBestDipPlanner(resolution=10, criterion=criterion).next(measurement, recon, candidates, k=8,
                                                                            operator=operator)
        assert not repeated_directions(chosen).any(), criterion
    ring = Reach(tilt_range_deg=(90, 90), step_deg=60).candidates()  # 6 directions on 3 lines
    with pytest.raises(ValueError, match=r"asked for 4 new dips, but only 3 of the 6 candidates are not measured"):
        NextBestDipPlanner(resolution=10).next(measurement, recon, ring, k=4, operator=operator)
