"""The surface refit: it moves a wrong surface to its dips when held-out dips license it, and keeps it otherwise."""

import copy

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.metrics import chamfer_hausdorff, evaluate, volume_surface
from dipnet.operators import make_operator
from dipnet.operators.mesh_slabs import mesh_slab_volumes
from dipnet.shapes import Ball, Box
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers import noise_covariance
from dipnet.solvers.optimize import target_and_sigma
from dipnet.solvers.surface_refit import NORMAL_TV_EPS, SurfaceRefit, _Fit
from dipnet.solvers.voxel import VoxelSolver
from tests.solvers.solver_helpers import one_thread, partial_volume  # noqa: F401  (one_thread: a fixture)

GRID = Grid(24, 3)
RADIUS = 30.0  # mm, in a 100 mm grid


def ball_problem(k: int = 24) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(directions (k, 3), slab edges (25,), exact slab volumes (k, 24))`` of the centred ball."""
    directions = fibonacci_hemisphere(k).double()
    edges = torch.linspace(-GRID.extent / 2, GRID.extent / 2, GRID.n + 1, dtype=torch.float64)
    below = Ball(RADIUS).volume_below(directions, edges)
    return directions, edges, torch.diff(below, dim=1)


def ball_result(radius: float) -> Reconstruction:
    return Reconstruction(partial_volume(GRID, lambda p: p.norm(dim=-1) < radius).float(), GRID, 0.5)


def mean_radius(mesh) -> float:
    return float(np.linalg.norm(mesh.vertices, axis=1).mean())


def test_a_surface_too_small_is_moved_to_its_exact_dips():
    directions, edges, slabs = ball_problem()
    start = ball_result(0.9 * RADIUS)
    before = mean_radius(volume_surface(start.occupancy, GRID, 0.5))
    recon = SurfaceRefit().refit(start, slabs, None, directions, edges)
    record = recon.info["surface_refit"]
    assert record["applied"] and record["heldout_gain"] > 0.5
    assert record["residual_after"] < record["residual_before"] / 5
    assert abs(mean_radius(recon.mesh) - RADIUS) < abs(before - RADIUS) / 4
    assert recon.mesh.is_watertight
    assert record["mesh_volume_mm3"] == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.01)
    assert record["volume_ratio"] == pytest.approx(1.0, abs=0.01)  # over the profiles' measured total


def noisy_ball(share: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(directions, edges, noisy slab volumes, sigma)``: white noise of ``share`` x the largest slab."""
    directions, edges, slabs = ball_problem()
    sigma = torch.full_like(slabs, share * float(slabs.max()))
    return directions, edges, slabs + sigma * torch.from_numpy(np.random.default_rng(0).normal(size=slabs.shape)), sigma


def readings_ball(snr_db: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """As :func:`noisy_ball`, the noise a level sensor gives at ``snr_db``: the ball dipped by the simulator and
    preprocessed (slab volumes the differences of cumulative readings, the sigma their stated noise)."""
    directions = fibonacci_hemisphere(24).double()
    sensor = LevelSensor(snr_db=snr_db, seed=0)
    _, measurement = simulate_measurement(Ball(RADIUS), directions, grid=GRID, sensor=sensor, seed=0, progress=False)
    operator = make_operator(GRID, measurement.directions, GRID.n)
    target, sigma, _ = target_and_sigma(measurement, operator)
    return operator.directions.double(), operator.slab_edges().double(), target, sigma


def test_a_surface_within_the_stated_noise_of_its_dips_is_kept_without_a_probe():
    directions, edges, noisy, sigma = noisy_ball(0.1)
    recon = SurfaceRefit(white_share=None).refit(ball_result(RADIUS), noisy, sigma, directions, edges)
    record = recon.info["surface_refit"]
    assert not record["applied"] and recon.mesh is None and record["noise_model"] == "independent"
    assert record["noise_ratio"] <= 1 + 3 * (2 / noisy.numel()) ** 0.5  # the noise's own ratio, 1 +- sqrt(2 / slabs)
    assert "stated noise" in record["reason"] and "heldout_gain" not in record


def test_a_wrong_surface_the_independent_model_calls_noise_is_refitted_under_the_readings_model():
    """10 dB from the readings: a ball 3 % too small (9 % of its volume) is within what independent slab errors
    allow, but its profiles' low frequencies (the cumulative volume) are 100 times the readings' noise off, so the
    readings model (the default) refits it, to about the noise's misfit."""
    directions, edges, noisy, sigma = readings_ball(10.0)
    kept = SurfaceRefit(white_share=None).refit(ball_result(0.97 * RADIUS), noisy, sigma, directions, edges)
    assert not kept.info["surface_refit"]["applied"] and "stated noise" in kept.info["surface_refit"]["reason"]
    record = SurfaceRefit().refit(ball_result(0.97 * RADIUS), noisy, sigma, directions, edges).info["surface_refit"]
    assert record["applied"] and record["noise_model"] == "readings" and record["noise_ratio"] > 50
    assert record["noise_ratio_after"] < 1.5 and "heldout_gain" not in record
    assert abs(record["volume_ratio"] - 1) < 0.01 < abs(kept.info["surface_refit"]["volume_ratio"] - 1) / 5


def test_with_a_stated_noise_the_refit_stops_where_the_misfit_reaches_the_noises():
    """The discrepancy principle: 30 dB, a ball 3 % too small, its misfit 39 x the noise's (independent slabs):
    the fit stops at the first step whose misfit is at most the noise's, long before its 150 steps."""
    directions, edges, noisy, sigma = readings_ball(30.0)
    record = SurfaceRefit(white_share=None).refit(ball_result(0.97 * RADIUS), noisy, sigma, directions,
                                                  edges).info["surface_refit"]
    assert record["applied"] and record["noise_ratio"] > 10 and 0 < record["steps_run"] < record["steps"] / 2
    assert 0.5 < record["noise_ratio_after"] <= 1.0
    assert f"until their misfit reached the noise's ({record['steps_run']} of 150 steps)" in record["reason"]


def test_held_out_dips_whose_misfit_turns_up_early_keep_the_surface_even_after_a_large_fall():
    """1 % noise, not stated: the probe cuts the held-out misfit by 40 %, then it rises from step 4 of 50 as the
    surface takes in the noise; a fall alone (min_gain) would have licensed the refit."""
    directions, edges, noisy, _ = noisy_ball(0.01)
    recon = SurfaceRefit().refit(ball_result(RADIUS), noisy, None, directions, edges)
    record = recon.info["surface_refit"]
    assert record["heldout_gain"] > 0.3 and record["heldout_best_step"] < 10
    assert not record["applied"] and recon.mesh is None and "turned up" in record["reason"]


def test_a_refit_that_ends_further_from_the_dips_keeps_the_surface_and_says_so(caplog):
    directions, edges, slabs = ball_problem()
    # steps of 40 mm: the mesh flies apart (and folds over: the folds are undone to reach the residual's judgement)
    wild = SurfaceRefit(lr=40.0, min_gain=0.0, still_falling=0.0, steps=20, unfold_passes=1000)
    recon = wild.refit(ball_result(0.9 * RADIUS), slabs, None, directions, edges)
    assert recon.mesh is None and not recon.info["surface_refit"]["applied"]
    assert "no closer to the dips" in recon.info["surface_refit"]["reason"]
    assert "no closer to the dips" in caplog.text


def folded(start, mesh) -> int:
    """Faces of ``mesh`` whose normal points against the same face's in ``start`` (the same faces)."""
    def normals(m):
        corners = m.vertices[m.faces]
        return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return int(((normals(start) * normals(mesh)).sum(1) < 0).sum())


def test_faces_the_refit_leaves_folded_over_are_unfolded_in_the_exported_surface(caplog):
    """1 mm steps without smoothness leave faces of the ball's surface folded over (a self-intersecting surface,
    though close to the dips): their corners are moved to their neighbours' mean, and the surface still fits."""
    directions, edges, slabs = ball_problem()
    start = ball_result(0.9 * RADIUS)
    rough = SurfaceRefit(lr=1.0, smoothness=0.0, min_gain=0.0, still_falling=0.0)
    recon = rough.refit(start, slabs, None, directions, edges)
    record = recon.info["surface_refit"]
    assert record["applied"] and record["folded_faces"] > 0 and record["folded_left"] == 0
    assert folded(volume_surface(start.occupancy, GRID, 0.5), recon.mesh) == 0
    assert record["residual_after"] < record["residual_before"] / 20
    assert f"the {record['folded_faces']} faces its last step folded over were unfolded" in record["reason"]


def test_a_surface_left_folded_over_is_not_taken_and_says_so(caplog):
    directions, edges, slabs = ball_problem()
    rough = SurfaceRefit(lr=1.0, smoothness=0.0, min_gain=0.0, still_falling=0.0, unfold_passes=0)
    recon = rough.refit(ball_result(0.9 * RADIUS), slabs, None, directions, edges)
    record = recon.info["surface_refit"]
    assert recon.mesh is None and not record["applied"] and record["folded_left"] == record["folded_faces"] > 0
    assert "intersects itself" in record["reason"] and "intersects itself" in caplog.text
    assert record["volume_ratio"] == pytest.approx(0.9**3, rel=0.05)  # the start's surface, as recorded


def test_the_default_refit_of_a_ball_folds_nothing():
    directions, edges, slabs = ball_problem()
    recon = SurfaceRefit().refit(ball_result(0.9 * RADIUS), slabs, None, directions, edges)
    assert recon.info["surface_refit"]["applied"] and "folded_faces" not in recon.info["surface_refit"]


def test_too_few_dips_to_hold_out_and_2d_results_are_kept_with_the_reason():
    directions, edges, slabs = ball_problem(k=8)
    recon = SurfaceRefit().refit(ball_result(0.9 * RADIUS), slabs, None, directions, edges)
    assert recon.mesh is None and "fewer than 2" in recon.info["surface_refit"]["reason"]
    flat = Reconstruction(torch.zeros(16, 16), Grid(16, 2), 0.5)
    assert "3D only" in SurfaceRefit().refit(flat, slabs, None, directions, edges).info["surface_refit"]["reason"]


@pytest.mark.parametrize("where", ["target", "sigma"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_slab_volumes_or_sigma_are_refused_by_name(where, bad):
    """A NaN slab made the probe's held-out misfit NaN, read as "fell by 0.0 % ...: a surface fitted closer would fit
    the dips' noise"; a NaN sigma ran 150 steps on NaN. Refused now, naming what holds it."""
    directions, edges, noisy, sigma = readings_ball(30.0)
    values = {"target": noisy.clone(), "sigma": sigma.clone()}
    values[where][3, 10] = bad
    name = "measured slab volumes" if where == "target" else "slab sigma"
    with pytest.raises(ValueError, match=f"surface refit: the {name} hold 1 NaN or infinite value"):
        SurfaceRefit().refit(ball_result(0.9 * RADIUS), values["target"], values["sigma"], directions, edges)


def test_evaluate_scores_the_refitted_mesh_when_there_is_one():
    directions, edges, slabs = ball_problem()
    truth = partial_volume(GRID, lambda p: p.norm(dim=-1) < RADIUS)
    start = ball_result(0.9 * RADIUS)
    voxel_score = evaluate(start, truth, GRID)["chamfer"]
    recon = SurfaceRefit().refit(start, slabs, None, directions, edges)
    score = evaluate(recon, truth, GRID)
    assert score["chamfer"] == chamfer_hausdorff(volume_surface(truth, GRID), recon.mesh)["chamfer"]
    assert score["chamfer"] < voxel_score / 2


@pytest.mark.parametrize("option, value", [("steps", 0), ("holdout_every", 1), ("lr", 0.0), ("smoothness", -1.0),
                                           ("min_gain", 1.0), ("probe_steps", 2.5), ("still_falling", 1.5),
                                           ("lr", None), ("smoothness", [1e-4]), ("still_falling", {}),
                                           ("unfold_passes", -1)])
def test_bad_options_are_refused_by_name(option, value):
    with pytest.raises(ValueError, match=f"surface_refit.{option}"):
        SurfaceRefit(**{option: value})


@pytest.mark.parametrize("value, message", [(True, "null \\(off\\) or a mapping"), ({"step": 10}, "not step")])
def test_a_solvers_surface_refit_option_that_is_no_mapping_of_its_options_is_refused(value, message):
    with pytest.raises(ValueError, match=message):
        VoxelSolver(surface_refit=value)


def test_the_voxel_solver_refits_its_surface_when_asked_and_says_why_not_with_a_fitted_gain():
    directions, edges, slabs = ball_problem()
    op = make_operator(GRID, directions)
    meas = DipMeasurement(op.directions, slabs, op.slab_thickness, edges[:1].expand(len(directions)))
    options = {"iterations": 60, "progress": False, "priors": {"tv": {"weight": 1e-3}}}
    recon = VoxelSolver(surface_refit={"steps": 60}, **options).solve(meas, op)
    assert recon.info["surface_refit"]["applied"] and recon.mesh is not None
    assert recon.info["surface_refit"]["steps"] == 60
    gained = VoxelSolver(surface_refit={}, fit_gain=True, **options).solve(meas, op)
    assert gained.mesh is None and "fit_gain" in gained.info["surface_refit"]["reason"]
    assert "surface_refit" not in VoxelSolver(**options).solve(meas, op).info


def test_slabs_too_many_for_the_readings_model_are_weighed_as_independent_and_say_so(monkeypatch):
    monkeypatch.setattr(noise_covariance, "PRECISION_ENTRIES", 100)
    directions, edges, noisy, sigma = readings_ball(30.0)
    record = SurfaceRefit().refit(ball_result(0.97 * RADIUS), noisy, sigma, directions, edges).info["surface_refit"]
    assert record["noise_model"].startswith("independent, the readings model's (24, 24) slabs being too many")
    assert record["applied"] and record["noise_ratio_after"] <= 1.0  # the independent model's discrepancy stop


def test_smoothed_profiles_are_weighed_as_independent_slabs_and_held_out_dips_decide():
    """Smoothed in preprocessing, a profile's errors are no longer the readings' differences: the readings model
    would call a surface thousands of times the noise off (3004 on the authors' smoothed cats, refitted for all its
    steps). So the slabs count as independent, and held-out dips decide, as without a stated noise."""
    directions, edges, noisy, sigma = readings_ball(30.0)
    record = SurfaceRefit().refit(ball_result(0.97 * RADIUS), noisy, sigma, directions, edges,
                                  differenced=False).info["surface_refit"]
    assert record["noise_model"].startswith("independent, the profiles being smoothed")
    assert record["noise_ratio"] == pytest.approx(SurfaceRefit(white_share=None).refit(
        ball_result(0.97 * RADIUS), noisy, sigma, directions, edges).info["surface_refit"]["noise_ratio"])
    assert "heldout_gain" in record and "steps_run" not in record


def test_the_normals_variation_of_a_box_counts_its_twelve_right_angled_edges():
    """A box's 12 triangles meet over 18 edges: 6 diagonals inside a face (normals equal: 0) and its 12 edges, where
    unit normals at right angles differ by sqrt(2)."""
    box = trimesh.creation.box(extents=(20.0, 30.0, 40.0))
    directions, edges, slabs = ball_problem(4)
    fit = _Fit(box, slabs, None, directions, edges, 0.0)
    eps = NORMAL_TV_EPS
    expected = 12 / 18 * ((2 + eps**2) ** 0.5 - eps)
    assert float(fit.normal_variation(torch.tensor(box.vertices))) == pytest.approx(expected, rel=1e-12)


def readings_box(snr_db: float) -> tuple[Box, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A 60 x 40 x 50 mm box dipped by the simulator at ``snr_db`` along 24 directions: ``(box, directions, edges,
    slab volumes, their sigma)``, as :func:`readings_ball`."""
    box = Box((30.0, 20.0, 25.0))
    directions = fibonacci_hemisphere(24).double()
    sensor = LevelSensor(snr_db=snr_db, seed=0)
    _, measurement = simulate_measurement(box, directions, grid=GRID, sensor=sensor, seed=0, progress=False)
    operator = make_operator(GRID, measurement.directions, GRID.n)
    target, sigma, _ = target_and_sigma(measurement, operator)
    return box, operator.directions.double(), operator.slab_edges().double(), target, sigma


def test_with_a_stated_noise_the_refit_runs_all_its_steps_under_the_normals_variation_weighted_from_the_noise():
    """20 dB, a box: the refit runs its 150 steps under the normals' variation, weighted 50 x the noise's expected
    relative misfit (``normal_tv``); with ``normal_tv=0`` it would stop where its misfit reaches the noise's, unweighted
    (test_with_a_stated_noise_the_refit_stops_where_the_misfit_reaches_the_noises)."""
    _, directions, edges, noisy, sigma = readings_box(20.0)
    start = Reconstruction(Box((30.0, 20.0, 25.0)).occupancy(GRID, supersample=3).float(), GRID, 0.5)
    record = SurfaceRefit().refit(copy.deepcopy(start), noisy, sigma, directions, edges).info["surface_refit"]
    assert record["applied"] and record["steps_run"] == record["steps"] == 150 and "total variation" in record["reason"]
    fit = _Fit(volume_surface(start.occupancy, GRID, 0.5), noisy, sigma, directions, edges, 0.0, 0.001)
    assert record["normal_tv_weight"] == pytest.approx(50 * fit.noise_relative_misfit(), rel=1e-9)
    assert fit.noise_relative_misfit() == pytest.approx(fit.noise_mean / float((noisy / sigma).pow(2).sum()))
    plain = SurfaceRefit(normal_tv=0.0).refit(copy.deepcopy(start), noisy, sigma, directions, edges)
    record = plain.info["surface_refit"]
    assert record["applied"] and "normal_tv_weight" not in record and "total variation" not in record["reason"]


def test_a_regularised_refit_that_ends_within_the_noise_is_taken_though_further_from_the_dips():
    """Under ``normal_tv`` a start that fits the dips closer than their noise may end a little further off, as the
    term trades fit for the normals' variation; within the noise's misfit that surface is taken (the discrepancy
    stop's rule, no closer to the dips -> kept, would throw away every such refit)."""
    directions, edges, _ = ball_problem()
    start = ball_result(RADIUS)
    mesh = volume_surface(start.occupancy, GRID, 0.5)
    exact = mesh_slab_volumes(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), directions, edges)
    sigma = torch.full_like(exact, 0.01 * float(exact.max()))
    fit = _Fit(mesh, exact, sigma, directions, edges, 0.0, 0.001)
    turn = torch.tensor([[1.0, -0.01, 0.0], [0.01, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    turned = fit.start @ turn.T  # about 0.6 deg about z: the same ball, another mesh
    assert fit.residual(fit.slabs(turned)) > fit.residual(fit.slabs(fit.start))
    assert fit.noise_ratio(fit.slabs(turned)) < fit.noise_limit()
    for regularised, applied in ((True, True), (False, False)):
        record = {"applied": False, "residual_before": fit.residual(fit.slabs(fit.start)), "noise_ratio": 0.0}
        recon = SurfaceRefit()._take(copy.deepcopy(start), mesh, fit, turned.clone(), "why", record, 0.0,
                                     float(exact.sum(1).median()), regularised)
        assert record["applied"] is applied and (recon.mesh is not None) is applied
        assert applied or "no closer to the dips" in record["reason"]


@pytest.mark.parametrize("solver", ["voxel_learned", "implicit_learned"])
def test_the_learned_solvers_configs_refit_with_the_modules_defaults(solver):
    """conf/surface_refit/default.yaml (both learned solvers' refit) states SurfaceRefit's own defaults, so the
    documented defaults and a job's refit are one; implicit_learned refits its field's result, not its start's."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"solver={solver}"])
    assert SurfaceRefit.from_options(OmegaConf.to_container(cfg.solver.surface_refit)) == SurfaceRefit()
    if solver == "implicit_learned":
        assert cfg.solver.warm_start.surface_refit is None
