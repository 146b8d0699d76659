"""Prior weights chosen from the data (the discrepancy principle, dipnet.solvers.weights)."""

from __future__ import annotations

import math

import pytest
import torch

from solver_helpers import noise_free_problem, one_thread  # noqa: F401 (one_thread: autouse fixture)
from dipnet.core.measurement import DipMeasurement
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.priors import build_priors
from dipnet.solvers.voxel import VoxelSolver
from dipnet.solvers.weights import DiscrepancyUpdate, WeightRule, auto_names, noise_level, with_weight


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
    assert rule["reason"].startswith("the weight whose solution's residual matches")
    assert 0.6 < rule["residual_reached"] / rule["target_residual"] < 1.5, rule
    assert rule["target_residual"] == pytest.approx(rule["tau"] * rule["noise_residual"])


def test_noise_below_the_reachable_residual_gets_the_floor_weight_and_says_why(clean):
    """Data whose noise (sigma 1e-5 of the rms slab) lies far below the residual the solver reaches."""
    _, op, meas = clean
    rec = VoxelSolver(progress=False).solve(noisy(meas, 1e-5), op)
    rule = rec.info["weight_rule"]
    assert rule["weight"] == pytest.approx(WeightRule().floor)
    assert "floor weight" in rule["reason"] and rule["residual_reached"] > rule["target_residual"]
    assert rule["updates"] and all(len(u) == 3 for u in rule["updates"])


def test_without_sigma_the_noise_is_estimated(clean):
    _, op, meas = clean
    rule = VoxelSolver(progress=False, iterations=60).solve(meas, op).info["weight_rule"]
    assert rule["noise_source"] == "estimated" and rule["noise_residual"] > 0


def test_a_fixed_weight_is_honoured(clean):
    _, op, meas = clean
    rec = VoxelSolver(progress=False, priors={"tv": {"weight": 3e-3}}).solve(noisy(meas, 0.1), op)
    assert rec.info["prior_weights"] == {"tv": 3e-3}
    assert rec.info["weight_rule"] == {"rule": "fixed"}


def test_update_settles_where_the_residual_meets_the_target():
    """A residual growing as ``w^0.4`` (as the voxel solver's does at 30 dB): the hook moves the
    weight to the one whose residual is the target, and stops moving after ``until``."""
    priors = build_priors({"tv": {"weight": 1e-3}, "binary": {"weight": 0.5}})
    rule = WeightRule(tau=1.0, every=1, until=0.5, gain=1.0)
    state = {}
    update = DiscrepancyUpdate(priors, ["tv"], lambda: 1e-3 * (state["w"] / 1e-2) ** 0.4, (4e-4, "sigma"), rule)
    for i in range(400):
        state["w"] = update.weight
        update(i / 400)
    expected = 1e-2 * 0.4 ** (1 / 0.4)
    assert update.weight == pytest.approx(expected, rel=0.02)
    assert dict((n, w) for n, w, _ in priors) == {"tv": update.weight, "binary": 0.5}  # only "auto" ones move
    assert update.trace[-1][0] < 200  # no update after `until`
    record = update.record(4e-4)
    assert record["target_residual"] == pytest.approx(math.sqrt(4e-4))


def test_weights_stay_within_floor_and_largest():
    rule = WeightRule(floor=1e-4, largest=1e-2, every=1, until=1.0)
    low = DiscrepancyUpdate(build_priors({"tv": 1e-3}), ["tv"], lambda: 1.0, (1e-6, "estimated"), rule)
    high = DiscrepancyUpdate(build_priors({"tv": 1e-3}), ["tv"], lambda: 1e-9, (1e-3, "sigma"), rule)
    for i in range(50):
        low(i / 50)
        high(i / 50)
    assert low.weight == pytest.approx(1e-4) and "floor" in low.record(1.0)["reason"]
    assert high.weight == pytest.approx(1e-2) and "largest" in high.record(1e-9)["reason"]


def test_noise_level_counts_filled_slabs_only():
    target = torch.tensor([[0.0, 0.0, 4.0, 2.0], [0.0, 3.0, 3.0, 0.0]], dtype=torch.float64)
    sigma = torch.full_like(target, 0.5)
    weight = torch.ones_like(target) / float(target.pow(2).sum())
    delta2, source = noise_level(target, sigma, weight)
    assert source == "sigma" and delta2 == pytest.approx(4 * 0.25 / 38)
    assert noise_level(target, None, weight)[1] == "estimated"


def test_auto_spec_helpers_and_bad_rules():
    spec = {"tv": {"weight": "auto", "isotropic": True}, "binary": {"weight": 0.0}, "l1": "auto"}
    assert auto_names(spec) == ["tv", "l1"]
    assert with_weight(spec, 2e-3) == {"tv": {"weight": 2e-3, "isotropic": True}, "binary": {"weight": 0.0},
                                       "l1": {"weight": 2e-3}}
    with pytest.raises(ValueError, match="unknown weight rule"):
        WeightRule(rule="sure")
    with pytest.raises(ValueError, match="floor <= start <= largest"):
        VoxelSolver(weight_rule={"floor": 1e-2, "start": 1e-3})
    with pytest.raises(ValueError, match="unknown prior"):
        VoxelSolver(priors={"tvv": {"weight": "auto"}})
