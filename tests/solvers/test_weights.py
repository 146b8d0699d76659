"""Prior weights chosen from the data (the discrepancy principle, dipnet.solvers.weights)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from solver_helpers import noise_free_problem, one_thread  # noqa: F401 (one_thread: autouse fixture)
from dipnet.core.measurement import DipMeasurement
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.voxel import VoxelSolver
from dipnet.solvers.weights import WeightRule, auto_names, noise_level, with_weight


def ellipse_with_bar(p: torch.Tensor) -> torch.Tensor:
    x, y = p[..., 0], p[..., 1]
    return ((x / 30) ** 2 + (y / 20) ** 2 < 1) | (((x - 20).abs() < 4) & ((y - 22).abs() < 12))


@pytest.fixture(scope="module")
def clean():
    """``(truth, operator, noise-free measurement)`` on 48^2 with 6 angles."""
    return noise_free_problem(2, ellipse_with_bar)


def noisy(measurement: DipMeasurement, relative: float, seed: int = 0) -> DipMeasurement:
    """``measurement`` with white noise of ``relative`` x its rms slab volume, and that sigma."""
    sigma = relative * float(measurement.profiles.pow(2).mean().sqrt())
    gen = torch.Generator().manual_seed(seed)
    noise = sigma * torch.randn(measurement.profiles.shape, generator=gen, dtype=torch.float64)
    return DipMeasurement(measurement.directions, measurement.profiles + noise, measurement.slab_thickness,
                          measurement.offsets, sigma=sigma)


def test_noisier_data_get_larger_weights(clean):
    _, op, meas = clean
    weights = []
    for relative in (0.02, 0.08, 0.3):
        rec = VoxelSolver(progress=False).solve(noisy(meas, relative), op)
        rule = rec.info["weight_rule"]
        assert rule["rule"] == "discrepancy" and rule["noise_source"] == "sigma"
        assert rec.info["prior_weights"]["tv"] == pytest.approx(rule["weight"])
        weights.append(rule["weight"])
    assert weights[0] < weights[1] < weights[2], weights


@pytest.mark.parametrize("solver", [VoxelSolver, ImplicitSolver], ids=["voxel", "implicit"])
def test_residual_of_the_chosen_weight_is_near_the_noise(clean, solver):
    _, op, meas = clean
    rec = solver(progress=False).solve(noisy(meas, 0.1), op)
    rule = rec.info["weight_rule"]
    assert rule["reason"] in ("the weight expected to bring the residual to tau times the noise",
                              "the first weight's solution already matches tau times the noise")
    assert 0.6 < rule["residual_reached"] / rule["target_residual"] < 1.5, rule
    assert rule["target_residual"] == pytest.approx(rule["tau"] * rule["noise_residual"])


def test_noise_below_the_reachable_residual_gets_the_floor_weight_and_says_why(clean):
    """Data whose noise (sigma 1e-5 of the rms slab) lies far below the residual the solver reaches."""
    _, op, meas = clean
    rec = VoxelSolver(progress=False).solve(noisy(meas, 1e-5), op)
    rule = rec.info["weight_rule"]
    assert rule["weight"] == pytest.approx(WeightRule().floor)
    assert "floor weight" in rule["reason"] and rule["residual_reached"] > rule["target_residual"]
    assert rule["refit_steps"] > 0 and rule["first_residual"] > rule["target_residual"]


@pytest.mark.parametrize("source", ["sigma", "readings"])
def test_a_known_noise_below_the_reachable_residual_is_not_called_noise_free(source):
    """The authors' real cats (64^3, the readings' noise 0.024 relative, the residual 0.080): metrics.json said "the
    noise lies below the residual the data allow (noise-free data)" of a recording whose noise is known and 3 times
    smaller than the model's misfit. A known noise names the model's error; an estimated one keeps the old reason."""
    rule = WeightRule()
    known = rule.record(rule.floor, 0.080**2, 0.080**2, (0.024**2, source))["reason"]
    assert "noise-free" not in known and f"(from the {source}): the model's own error" in known
    assert known.endswith("floor weight")
    estimated = rule.record(rule.floor, 0.080**2, 0.080**2, (0.024**2, "estimated"))["reason"]
    assert estimated == "the noise lies below the residual the data allow (noise-free data): floor weight"


def test_an_estimated_noise_never_raises_the_weight(clean):
    """Noise-free data the grid reproduces exactly: the estimate reads the profiles' curvature as
    noise (about the residual here); the weight may fall, never rise above the start."""
    _, op, meas = clean
    rule = VoxelSolver(progress=False).solve(meas, op).info["weight_rule"]
    assert rule["noise_source"] == "estimated" and rule["noise_residual"] > 0
    assert rule["weight"] <= WeightRule().start


def test_an_unstated_noise_is_taken_from_the_readings(clean):
    """No stated sigma, but the per-slab sigma preprocessing found in the readings' own scatter
    (``metadata["readings_slab_sigma"]``): the weight the stated sigma gets, where the profiles' own estimate may
    only lower it; a value that is no positive number is not taken."""
    _, op, meas = clean
    stated = noisy(meas, 0.1)
    sigma = float(stated.sigma.max())
    known = VoxelSolver(progress=False).solve(stated, op).info["weight_rule"]
    readings = VoxelSolver(progress=False).solve(
        replace(stated, sigma=None, metadata={"readings_slab_sigma": sigma}), op).info["weight_rule"]
    assert readings["noise_source"] == "readings" and readings["weight"] == pytest.approx(known["weight"], rel=1e-6)
    assert readings["noise_residual"] == pytest.approx(known["noise_residual"], rel=1e-6)
    for bad in (None, 0.0, -1.0, float("nan"), True, "3"):
        unknown = VoxelSolver(progress=False).solve(replace(stated, sigma=None, metadata={"readings_slab_sigma": bad}),
                                                    op).info["weight_rule"]
        assert unknown["noise_source"] == "estimated" and unknown["weight"] <= WeightRule().start, bad


def test_a_fixed_weight_is_honoured(clean):
    _, op, meas = clean
    rec = VoxelSolver(progress=False, priors={"tv": {"weight": 3e-3}}).solve(noisy(meas, 0.1), op)
    assert rec.info["prior_weights"] == {"tv": 3e-3}
    assert rec.info["weight_rule"] == {"rule": "fixed"}


def test_next_weight_steps_toward_the_target_along_the_assumed_slope():
    rule = WeightRule(tau=0.5, slope=0.5, tolerance=0.1, floor=1e-4, largest=1e-1)
    goal = rule.target(4e-4)
    assert goal == pytest.approx(1e-4)
    # D = 1e-4 (w / 1e-3)^0.5 meets the goal at w = 1e-3: one step from either side lands there
    for start in (1e-4 * 3, 3e-3):
        assert rule.next_weight(start, 1e-4 * (start / 1e-3) ** 0.5, 4e-4) == pytest.approx(1e-3)
    assert rule.next_weight(2e-3, 1.05e-4, 4e-4) == 2e-3  # within the tolerance: kept
    assert rule.next_weight(1e-3, 1.0, 4e-4) == 1e-4  # far above the noise: the floor
    assert rule.next_weight(1e-3, 1e-12, 4e-4) == 1e-1  # far below: the largest
    assert rule.next_weight(1e-3, 1e-3, 0.0) == 1e-4  # no noise at all: the floor
    assert rule.next_weight(1e-3, 1e-12, 4e-4, may_raise=False) == 1e-3  # an estimated noise only lowers
    assert rule.next_weight(1e-3, 1.0, 4e-4, may_raise=False) == 1e-4


def test_record_says_why():
    rule = WeightRule()
    assert "floor" in rule.record(rule.floor, 1e-2, 1e-2, (1e-6, "estimated"))["reason"]
    assert "largest" in rule.record(rule.largest, 1e-9, 1e-9, (1e-3, "sigma"))["reason"]
    kept = rule.record(rule.start, rule.target(1e-3), 1e-4, (1e-3, "sigma"))
    assert "already matches" in kept["reason"] and kept["noise_source"] == "sigma"
    assert kept["noise_residual"] == pytest.approx(math.sqrt(1e-3)) and kept["residual_reached"] == pytest.approx(1e-2)


def test_noise_level_counts_filled_slabs_only():
    target = torch.tensor([[0.0, 0.0, 4.0, 2.0], [0.0, 3.0, 3.0, 0.0]], dtype=torch.float64)
    sigma = torch.full_like(target, 0.5)
    weight = torch.ones_like(target) / float(target.pow(2).sum())
    delta2, source = noise_level(target, sigma, weight)
    assert source == "sigma" and delta2 == pytest.approx(4 * 0.25 / 38)
    assert noise_level(target, None, weight)[1] == "estimated"


def test_auto_spec_helpers_and_bad_rules():
    spec = {"tv": {"weight": "auto", "isotropic": True}, "binary": {"weight": 0.0}, "l1": "auto", "volume": 0.5}
    assert auto_names(spec) == ["tv", "l1"]
    assert with_weight(spec, 2e-3) == {"tv": {"weight": 2e-3, "isotropic": True}, "binary": {"weight": 0.0},
                                       "l1": {"weight": 2e-3}, "volume": {"weight": 0.5}}
    with pytest.raises(ValueError, match="give a number or 'auto'"):
        VoxelSolver(priors={"tv": {"weight": "automatic"}})
    with pytest.raises(ValueError, match="unknown weight rule"):
        WeightRule(rule="sure")
    with pytest.raises(ValueError, match="floor <= start <= largest"):
        VoxelSolver(weight_rule={"floor": 1e-2, "start": 1e-3})
    for name in ("tau", "slope", "largest", "tolerance", "refit_lr"):  # was: run, tau=inf at the largest weight
        with pytest.raises(ValueError, match=f"the weight rule's {name} must be finite"):
            VoxelSolver(weight_rule={name: math.inf})
    with pytest.raises(ValueError, match="weight_rule takes rule, tau, .*; not taux"):
        VoxelSolver(weight_rule={"taux": 1.0})  # was: a TypeError, "an option of the wrong type" in a job
    with pytest.raises(ValueError, match="unknown prior"):
        VoxelSolver(priors={"tvv": {"weight": "auto"}})
