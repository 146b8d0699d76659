"""VoxelSolver and the shared optimisation loop: recovery beyond min-norm, options, reproducibility."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from solver_helpers import FIXED_TV, noise_free_problem, one_thread  # noqa: F401 (one_thread: autouse fixture)
from dipnet.core.grid import Grid
from dipnet.evaluation.metrics import iou
from dipnet.operators import make_operator
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.shapes import Ball, Box
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.optimize import DataTerm, optimise, plateaued, support_hull
from dipnet.solvers.voxel import VoxelSolver


def blobs_2d(p: torch.Tensor) -> torch.Tensor:
    """A tilted ellipse with a hole, a square and a bar (mm, in a 100 mm grid)."""
    x, y = p[..., 0], p[..., 1]
    u, v = (x - 4) * 0.8 + (y + 2) * 0.6, -(x - 4) * 0.6 + (y + 2) * 0.8
    ellipse = (u / 30) ** 2 + (v / 18) ** 2 < 1
    hole = (x + 2) ** 2 + (y - 3) ** 2 < 8**2
    square = ((x + 28).abs() < 7) & ((y - 26).abs() < 7)
    bar = ((x - 22).abs() < 4) & ((y - 20).abs() < 14)
    return (ellipse & ~hole) | square | bar


def problem(ndim: int):
    """``(truth, operator, measurement)`` for this file's 2D shape or the hollow ellipsoid."""
    return noise_free_problem(ndim, blobs_2d)


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def case(request):
    return problem(request.param)


# The floors sit between min-norm (2D 0.91, 3D 0.81 measured) and the voxel solver (0.98, 0.97).
FLOORS = {2: 0.95, 3: 0.92}


def test_recovers_shape_that_minnorm_misses(case):
    truth, op, meas = case
    floor = FLOORS[op.grid.ndim]
    baseline = MinNormSolver(progress=False).solve(meas, op)
    rec = VoxelSolver(progress=False, priors=FIXED_TV).solve(meas, op)
    assert iou(baseline.binary, truth > 0.5) < floor
    assert iou(rec.binary, truth > 0.5) >= floor
    assert rec.occupancy.shape == op.grid.shape and 0 <= float(rec.occupancy.min()) <= float(rec.occupancy.max()) <= 1
    assert float(rec.occupancy[~op.mask].abs().max()) == 0.0  # outside the working ball stays empty
    hist = rec.history
    assert set(hist) == {"loss", "data", "tv"} and len(hist["loss"]) == rec.info["iterations"]
    assert hist["data"][-1] < 0.01 * hist["data"][0]
    assert [s["n"] for s in rec.info["stages"]] == [op.grid.n // 2, op.grid.n]


def test_seeded_runs_are_reproducible():
    _, op, meas = problem(2)
    a = VoxelSolver(iterations=60, seed=3, progress=False).solve(meas, op)
    b = VoxelSolver(iterations=60, seed=3, progress=False).solve(meas, op)
    assert torch.equal(a.occupancy, b.occupancy) and a.history == b.history


def test_annealing_makes_the_result_more_binary():
    _, op, meas = problem(2)
    opts = dict(iterations=120, coarse_to_fine=False, progress=False)
    soft = VoxelSolver(temperature_start=1.0, temperature_end=1.0, **opts).solve(meas, op)
    hard = VoxelSolver(temperature_start=1.0, temperature_end=0.05, **opts).solve(meas, op)

    def grey(r):
        return float((r.occupancy * (1 - r.occupancy))[op.mask].mean())

    assert grey(hard) < 0.5 * grey(soft)


def test_warm_start_from_solver_tensor_or_callable():
    truth, op, meas = problem(2)
    opts = dict(iterations=1, coarse_to_fine=False, temperature_end=1.0, progress=False, lr=1e-6)
    from_truth = VoxelSolver(warm_start=truth.float(), **opts).solve(meas, op)
    assert iou(from_truth.binary, truth > 0.5) > 0.97  # one tiny step keeps the start
    from_solver = VoxelSolver(warm_start=MinNormSolver(progress=False), **opts).solve(meas, op)
    from_callable = VoxelSolver(warm_start=lambda m, o: MinNormSolver(progress=False).solve(m, o), **opts)
    torch.testing.assert_close(from_solver.occupancy, from_callable.solve(meas, op).occupancy)
    with pytest.raises(ValueError, match="warm start has shape"):
        VoxelSolver(warm_start=torch.zeros(5, 5), **opts).solve(meas, op)
    for bad in (5, "minnorm", {"iterations": 3}):  # 5 was refused only after the simulation, naming a shape ()
        with pytest.raises(ValueError, match=r"warm_start must be null, a solver .*got"):
            VoxelSolver(warm_start=bad, **opts)


def test_early_stopping_and_lbfgs():
    _, op, meas = problem(2)
    stopped = VoxelSolver(iterations=400, tol=0.5, window=5, progress=False).solve(meas, op)
    assert stopped.info["iterations"] < 400
    lbfgs = VoxelSolver(optimizer="lbfgs", lr=1.0, iterations=30, coarse_to_fine=False, temperature_end=1.0,
                        progress=False, priors=FIXED_TV).solve(meas, op)
    assert lbfgs.history["data"][-1] < 0.05 * lbfgs.history["data"][0]


def test_data_term_is_relative_and_sigma_weighted():
    truth, op, meas = problem(2)
    plain = DataTerm(op, meas.profiles, dtype=torch.float64)
    assert float(plain(torch.zeros_like(truth))) == pytest.approx(1.0)
    assert float(plain(truth)) == pytest.approx(0.0, abs=1e-20)
    corrupted = meas.profiles.clone()
    corrupted[0] *= 2  # orientation 0 is wrong ...
    sigma = torch.ones_like(corrupted)
    sigma[0] = 1e6  # ... and says so: its residual must not count
    assert float(DataTerm(op, corrupted, dtype=torch.float64)(truth)) > 0.01
    assert float(DataTerm(op, corrupted, sigma, dtype=torch.float64)(truth)) < 1e-9
    assert float(DataTerm(op, corrupted, sigma, dtype=torch.float64)(torch.zeros_like(truth))) == pytest.approx(1.0)


def test_optimise_validates_and_records_history():
    _, op, meas = problem(2)
    z = torch.zeros(op.grid.shape, requires_grad=True)
    data = DataTerm(op, meas.profiles)
    with pytest.raises(ValueError, match="optimizer"):
        optimise([z], lambda: torch.sigmoid(z), data, [], iterations=2, lr=0.1, optimizer="sgd")
    hist = optimise([z], lambda: torch.sigmoid(z), data, [], iterations=5, lr=0.1, schedule="step", progress=False)
    assert set(hist) == {"loss", "data"} and len(hist["loss"]) == 5 and hist["loss"][-1] < hist["loss"][0]
    with pytest.raises(ValueError, match="schedule"):
        VoxelSolver(schedule="linear")
    with pytest.raises(ValueError, match="unknown prior"):
        VoxelSolver(priors={"tvv": {"weight": 1.0}})


@pytest.mark.parametrize("option,message", [
    ({"later_priors": 5}, r"later_priors must be null or a mapping \{prior: options\}.*got 5"),  # 'int' ... 'items'
    ({"priors": 5}, r"priors must be null or a mapping \{prior: options\}.*got 5"),
    ({"rounds_tau": "abc"}, r"rounds_tau must be a positive, finite number or null .*got 'abc'"),  # '>' not supported
    ({"coarse_fraction": "abc"}, r"coarse_fraction must be in \[0, 1\), got 'abc'"),  # '<=' not supported
])
def test_options_of_the_wrong_type_are_refused_naming_the_option(option, message):
    with pytest.raises(ValueError, match=message):
        VoxelSolver(**option)


def test_plateau_test_stops_on_a_flat_loss_and_not_on_a_falling_one():
    flat_after_10 = [1.0 / (i + 1) for i in range(10)] + [0.1] * 40
    assert plateaued(flat_after_10, tol=1e-3, window=10)
    falling = [1.0 - 0.01 * i for i in range(50)]  # 1% better every step: never a plateau
    assert not any(plateaued(falling[:n], tol=1e-3, window=10) for n in range(1, 51))
    jitter = [0.5 + 0.01 * (i % 2) for i in range(40)]  # Adam-like jitter around a flat level
    assert plateaued(jitter, tol=1e-3, window=10) and not plateaued(jitter, tol=0.0, window=10)

    # in the loop: a loss that cannot move (the occupancy ignores the parameter) stops after
    # two windows, long before the iteration limit
    _, op, meas = problem(2)
    z = torch.zeros(1, requires_grad=True)
    fixed = torch.full(op.grid.shape, 0.5)
    hist = optimise([z], lambda: fixed + 0 * z, DataTerm(op, meas.profiles), [], iterations=500, lr=0.1,
                    tol=1e-3, window=20, progress=False)
    assert len(hist["loss"]) == 40


@pytest.mark.parametrize("ndim", [2, 3])
def test_support_hull_holds_the_object_and_carves_the_ball(ndim):
    truth, op, meas = problem(ndim)
    hull = support_hull(meas.profiles, op.grid, op.directions, op.slab_edges())
    assert not bool((truth > 0)[~hull].any())  # every partly occupied voxel stays available
    assert int(hull.sum()) < 0.8 * int(op.mask.sum()) and not bool(hull[~op.mask].any())
    rec = VoxelSolver(iterations=5, progress=False).solve(meas, op)
    assert float(rec.occupancy[~hull].abs().max()) == 0.0
    assert rec.info["support_voxels"] == int(hull.sum())


def test_hull_margin_widens_the_support_and_is_validated():
    truth, op, meas = problem(3)
    tight = VoxelSolver(progress=False).support(meas.profiles, op, op.grid)
    loose = VoxelSolver(progress=False, hull_margin=4.0).support(meas.profiles, op, op.grid)
    assert bool((loose | ~tight).all()) and int(loose.sum()) > int(tight.sum())  # a superset, strictly larger
    with pytest.raises(ValueError, match="hull_margin"):
        VoxelSolver(hull_margin=-1.0)


@pytest.mark.parametrize("shape", [Ball(25.0),
                                   pytest.param(Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0)), marks=pytest.mark.slow)],
                         ids=["ball", "box"])
def test_fit_gain_recovers_a_common_volume_factor(shape):
    """Every measured volume x 1.1 (a tank 9 % smaller than assumed): with ``fit_gain`` the solver
    finds the factor (within 2.5 %) and the object's true volume; without it the shape swells."""
    grid = Grid(32, extent=80.0)
    _, m = simulate_measurement(shape, fibonacci_hemisphere(24), grid=grid, progress=False)
    m.profiles = m.profiles * 1.1
    op = make_operator(grid, m.directions, grid.n)
    fitted = VoxelSolver(iterations=150, progress=False, fit_gain=True).solve(m, op)
    plain = VoxelSolver(iterations=150, progress=False).solve(m, op)
    voxel = grid.voxel_size**3
    assert fitted.info["gain"] == pytest.approx(1.1, rel=0.025)
    assert fitted.binary.sum() * voxel == pytest.approx(shape.volume, rel=0.03)
    assert "gain" not in plain.info and plain.binary.sum() * voxel > 1.05 * shape.volume


def test_volume_threshold_encloses_the_measured_volume_over_the_gain():
    """``threshold="volume"``: the result's surface encloses what the dips measure, divided by the
    fitted gain (every volume x 1.1 here), so the ball's true volume; the level is recorded."""
    grid = Grid(32, extent=80.0)
    ball = Ball(25.0)
    _, m = simulate_measurement(ball, fibonacci_hemisphere(24), grid=grid, progress=False)
    m.profiles = m.profiles * 1.1
    op = make_operator(grid, m.directions, grid.n)
    rec = VoxelSolver(iterations=150, progress=False, fit_gain=True, threshold="volume").solve(m, op)
    rule = rec.info["threshold_rule"]
    assert rule["rule"] == "volume" and rule["level"] == rec.threshold and 0.25 < rec.threshold < 0.75
    assert rule["measured_volume_mm3"] == pytest.approx(1.1 * ball.volume / rec.info["gain"], rel=1e-6)
    assert rule["enclosed_volume_mm3"] == pytest.approx(rule["measured_volume_mm3"], rel=2e-3)
    assert rule["enclosed_volume_mm3"] == pytest.approx(ball.volume, rel=0.03)
    assert "threshold_rule" not in VoxelSolver(iterations=5, progress=False).solve(m, op).info
    with pytest.raises(ValueError, match="threshold"):
        VoxelSolver(threshold="otsu")


def test_data_term_gain_scales_the_prediction():
    """``a A o`` with ``a = exp(log_gain)``: the data term vanishes at the right gain, and the gain
    is a parameter only with ``fit_gain``."""
    grid = Grid(16, extent=80.0)
    _, m = simulate_measurement(Ball(25.0), fibonacci_hemisphere(8), grid=grid, progress=False)
    op = make_operator(grid, m.directions, grid.n)
    occ = Ball(25.0).occupancy(grid, supersample=3).float()
    target = op(occ).detach()
    data = DataTerm(op, 1.25 * target, fit_gain=True, log_gain=math.log(1.25))
    assert float(data(occ).detach()) < 1e-10 and data.gain == pytest.approx(1.25)
    assert [name for name, _ in data.named_parameters()] == ["log_gain"]
    assert DataTerm(op, target).log_gain is None and DataTerm(op, target).gain == 1.0


def test_rounds_chain_solves_each_warm_started_from_the_last():
    """``rounds=2`` is the solve, then the same solve warm-started from its result."""
    _, op, meas = problem(2)
    opts = dict(iterations=40, coarse_to_fine=False, progress=False, priors=FIXED_TV, seed=2)
    first = VoxelSolver(**opts).solve(meas, op)
    second = VoxelSolver(warm_start=first.occupancy, **opts).solve(meas, op)
    chained = VoxelSolver(rounds=2, **opts).solve(meas, op)
    assert torch.allclose(chained.occupancy, second.occupancy, atol=1e-6)
    assert [s["round"] for s in chained.info["stages"]] == [1, 2]
    assert len(chained.history["loss"]) == len(first.history["loss"]) + len(second.history["loss"])
    with pytest.raises(ValueError, match="rounds"):
        VoxelSolver(rounds=0)
    with pytest.raises(ValueError, match="rounds must be a whole number"):
        VoxelSolver(rounds=2.5)  # was: 2 rounds run unsaid
    with pytest.raises(ValueError, match="min_rounds must be a whole number"):
        VoxelSolver(rounds=3, min_rounds=1.5)


def test_rounds_stop_when_the_data_term_exceeds_the_noise_target():
    """``rounds_tau``: with the measurement's sigma, the discrepancy principle ends the rounds after the
    first whose data term is above ``rounds_tau^2`` x the noise's, and a loose target lets every round
    run; a noise only estimated from the profiles never licenses a second round."""
    _, op, meas = problem(2)
    noisy = dataclasses.replace(meas, sigma=torch.full_like(meas.profiles, 0.01 * float(meas.profiles.max())))
    opts = dict(iterations=30, coarse_to_fine=False, progress=False, priors=FIXED_TV, seed=2, rounds=3)
    one = VoxelSolver(**{**opts, "rounds": 1}).solve(noisy, op)
    strict = VoxelSolver(rounds_tau=1e-6, **opts).solve(noisy, op)
    loose = VoxelSolver(rounds_tau=1e6, **opts).solve(noisy, op)
    estimated = VoxelSolver(rounds_tau=1e6, **opts).solve(meas, op)
    assert strict.info["rounds"]["done"] == 1 and strict.info["rounds"]["stopped"]
    assert torch.allclose(strict.occupancy, one.occupancy)
    assert loose.info["rounds"]["done"] == 3 and not loose.info["rounds"]["stopped"]
    record = loose.info["rounds"]
    assert record["rule"] == "discrepancy" and record["noise_source"] == "sigma"
    assert record["residual"] == pytest.approx(loose.history["data"][-1] ** 0.5)
    assert record["target_residual"] == pytest.approx(1e6 * record["noise_residual"])
    assert estimated.info["rounds"]["done"] == 1 and "estimated" in estimated.info["rounds"]["reason"]
    with pytest.raises(ValueError, match="rounds_tau"):
        VoxelSolver(rounds_tau=0.0)


def test_min_rounds_run_whatever_the_rule_says_and_later_priors_change_them():
    """The first ``min_rounds`` rounds run even when the rule would stop them; ``later_priors`` are
    merged over ``priors`` for rounds 2 and on (here a heavier TV), and the result reports them."""
    _, op, meas = problem(2)
    opts = dict(iterations=30, coarse_to_fine=False, progress=False, priors=FIXED_TV, seed=2, rounds=3,
                rounds_tau=1e-6)
    forced = VoxelSolver(min_rounds=2, later_priors={"tv": {"weight": 0.05}}, **opts).solve(meas, op)
    assert forced.info["rounds"]["done"] == 2 and forced.info["rounds"]["stopped"]
    assert forced.info["prior_weights"]["tv"] == 0.05
    one = VoxelSolver(**opts).solve(meas, op)
    assert one.info["rounds"]["done"] == 1 and one.info["prior_weights"]["tv"] == 1e-3
    merged = VoxelSolver(**{**opts, "priors": {"tv": {"weight": 1e-3, "isotropic": False}}},
                         later_priors={"tv": 0.05}).later_priors  # a bare number is the weight; other options stay
    assert merged == {"tv": {"weight": 0.05, "isotropic": False}}
    with pytest.raises(ValueError, match="min_rounds"):
        VoxelSolver(rounds=2, min_rounds=3)
    with pytest.raises(ValueError, match="unknown prior"):
        VoxelSolver(later_priors={"nonsense": {"weight": 1.0}})


@pytest.mark.parametrize("start, end", [(math.inf, math.inf), (math.inf, 0.25), (1.0, math.nan), ("1", 0.25)])
def test_temperatures_must_be_finite_and_annealing(start, end):
    """An infinite temperature flattened every logit to 0.5: a NaN loss named as a divergence, "try a lower lr"."""
    with pytest.raises(ValueError, match="need finite temperatures 0 < temperature_end <= temperature_start"):
        VoxelSolver(temperature_start=start, temperature_end=end)
