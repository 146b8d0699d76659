"""End-to-end: Hydra configs compose, the job runs, and bad input gets a one-line error."""

import json
import math
import os

import numpy as np
import pytest
import torch
import trimesh
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import OmegaConf

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.jobs.pipeline import run, saved_frame, write_outputs
from dipnet.solvers.denoiser import PriorMismatchError

from planning_fixtures import reconstruct_cfg, tilt_spin

QUIET = ["output.progress=false"]


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[*QUIET, *overrides])


#: The solvers every option test composes and instantiates (each with its progress bars on and off).
SOLVERS = ("minnorm", "lsqr", "lsmr", "voxel", "implicit", "voxel_learned", "implicit_learned")


@pytest.mark.parametrize("group,options", [
    # the solver group's options compose and instantiate in test_one_switch_sets_every_progress_bar (the same
    # configs: output.progress=false is in every _cfg), not twice
    ("operator", ["auto", "splat", "rotate_sum", "grid_sample"]),
])
def test_config_groups_compose_and_instantiate(group, options):
    for option in options:
        cfg = _cfg(f"{group}={option}")
        assert instantiate(cfg[group]) is not None


def _not_json(word: str) -> None:
    raise ValueError(f"metrics.json holds {word}, which is not JSON")


def test_2d_end_to_end_reaches_the_iou_floor(tmp_path):
    # 64 pixels (was 128: the second solve cost 1.3 s, now 0.5 s): IoU 0.994 measured (0.996 at 128), the floor
    # stays 0.95; the saved measurement's solve agrees on every pixel at both sizes
    result = run(_cfg("ndim=2", "resolution=64", "n_dips=20"), tmp_path)
    assert result.metrics["iou"] >= 0.95
    saved = json.loads((tmp_path / "metrics.json").read_text(), parse_constant=_not_json)  # strict JSON
    assert saved["iou"] == pytest.approx(result.metrics["iou"])
    assert all(saved[k] is None for k, v in result.metrics.items() if isinstance(v, float) and not math.isfinite(v))
    for name in ("reconstruction.npz", "measurement.npz", "rawscan.jsonl", "sinogram.png", "slices.png",
                 "profiles.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    # the saved measurement reconstructs the same way as a recorded source
    again = run(_cfg("ndim=2", "resolution=64", "source=recorded",
                     f"source.reader.path={tmp_path / 'measurement.npz'}", "output.figures=false"),
                tmp_path / "recorded")
    assert (again.reconstruction.binary == result.reconstruction.binary).mean() > 0.999


@pytest.mark.slow
def test_3d_end_to_end_reaches_the_iou_floor(tmp_path):
    result = run(_cfg("resolution=32", "n_dips=100", "shape.name=ball", "output.figures=false"), tmp_path)
    assert result.metrics["iou"] >= 0.85
    assert (tmp_path / "reconstruction.ply").stat().st_size > 0 and (tmp_path / "truth.ply").stat().st_size > 0
    measured = DipMeasurement.load(tmp_path / "measurement.npz")
    assert measured.profiles.shape == (100, 32)


def test_a_job_with_the_surface_refit_exports_and_scores_the_refitted_mesh(tmp_path):
    result = run(_cfg("resolution=24", "n_dips=24", "shape.name=ball", "solver=voxel", "solver.iterations=80",
                      "solver.surface_refit={steps: 60}", "output.figures=false", "output.uncertainty=false",
                      "output.resolvability=false"), tmp_path)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["surface_refit"] == "refitted" and "held-out" in saved["surface_refit_reason"]
    exported = trimesh.load(tmp_path / "reconstruction.ply")
    assert exported.is_watertight
    assert abs(exported.volume) == pytest.approx(saved["surface_volume_mm3"], rel=1e-6)
    assert np.allclose(exported.vertices, result.reconstruction.mesh.vertices, atol=1e-4)  # the refitted mesh
    assert saved["surface_residual"] < result.reconstruction.info["surface_refit"]["residual_before"]


@pytest.fixture
def cli(script_run):
    """``python scripts/reconstruct.py hydra.run.dir=<dir> ...`` in this process (tests/script_runs.py: the same
    exit code and output without the ~6 s a subprocess spends importing torch; tests/fuzz/test_bad_data.py keeps
    a real subprocess of the script)."""
    return lambda run_dir, *overrides: script_run("reconstruct", run_dir, *QUIET, *overrides)


@pytest.mark.parametrize("overrides,message", [
    (["resolution=-4"], "resolution must be"),
    pytest.param(["n_dips=0"], "n_dips must be a positive integer", marks=pytest.mark.slow),
    pytest.param(["shape=mesh", "shape.path=/nonexistent/bunny.stl"], "/nonexistent/bunny.stl", marks=pytest.mark.slow),
    pytest.param(["source=recorded", "source.reader.path=/nonexistent/m.npz"], "/nonexistent/m.npz",
                 marks=pytest.mark.slow),
])
def test_bad_input_gets_a_one_line_error(tmp_path, cli, overrides, message):
    proc = cli(tmp_path, *overrides)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert message in proc.stderr


def test_a_fill_too_small_for_one_voxel_is_named_before_any_dip(tmp_path, cli):
    """fill=1e-9 was refused after the dips were simulated, naming an extent_mm=1.08e+11 the user never set."""
    proc = cli(tmp_path, "resolution=12", "n_dips=4", "fill=1e-9")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "error: fill must be in [0.181, 1] for this object at resolution 12" in proc.stderr
    assert "got 1e-09" in proc.stderr and not (tmp_path / "measurement.npz").exists()


@pytest.mark.slow
def test_malformed_measurement_and_unknown_option(tmp_path, cli):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"garbage")
    proc = cli(tmp_path / "a", "source=recorded", f"source.reader.path={bad}")
    assert proc.returncode == 2 and "bad.npz" in proc.stderr and "Traceback" not in proc.stderr
    proc = cli(tmp_path / "b", "solver=nonsense")
    assert proc.returncode != 0 and "solver" in proc.stderr and "Traceback" not in proc.stderr


def test_prior_weights_and_warm_start_override_from_the_command_line():
    """The overrides reach the solver: the priors it builds carry the given weights and options,
    and its warm start is a quiet min-norm solver."""
    from dipnet.solvers import MinNormSolver
    from dipnet.solvers.priors import build_priors

    cfg = _cfg("solver=voxel", "solver.priors.tv.weight=0.1", "solver.priors.symmetry.weight=0.5",
               "solver.priors.symmetry.plane_normal=[1,0,0]",
               "+solver.warm_start={_target_: dipnet.solvers.MinNormSolver, progress: false}")
    solver = instantiate(cfg.solver)
    assert type(solver).__name__ == "VoxelSolver"
    built = {name: (weight, module) for name, weight, module in build_priors(solver.priors, volume_fraction=0.1)}
    assert set(built) == {"tv", "symmetry"}  # every other prior keeps weight 0 (off)
    assert built["tv"][0] == 0.1 and built["symmetry"][0] == 0.5
    assert list(built["symmetry"][1].plane_normal) == [1, 0, 0]
    assert isinstance(solver.warm_start, MinNormSolver) and solver.warm_start.progress is False


@pytest.mark.parametrize("progress", [True, False])
def test_one_switch_sets_every_progress_bar(progress):
    """Also: every option of the solver config group composes and instantiates."""
    for solver in SOLVERS:
        built = instantiate(_cfg(f"solver={solver}", f"output.progress={progress}").solver)
        assert built is not None, f"solver={solver} did not instantiate"
        while built is not None:  # the solver and each warm start it nests (implicit_learned: two)
            assert built.progress is progress, solver
            built = getattr(built, "warm_start", None)
            built = built if hasattr(built, "solve") else None


def test_thread_count_defaults_never_oversubscribe(monkeypatch):
    from dipnet.jobs import threads

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    try:
        assert threads.default_threads(multirun=True) == 1
        assert threads.default_threads(multirun=False) == threads.available_cores() == len(os.sched_getaffinity(0))
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        assert threads.configure_threads(None, multirun=False) == 1 == torch.get_num_threads()
        assert threads.configure_threads(2) == 2 == torch.get_num_threads()
        with pytest.raises(ValueError, match="threads must be a positive integer"):
            threads.configure_threads(0)
    finally:
        torch.set_num_threads(before)


def test_an_object_keeps_its_size_in_mm_at_any_resolution(tmp_path):
    """The grid is chosen around the object: at 16 and 24 voxels the chamber box is the same
    52 mm cube (same measured volume to 0.1%), and volume_error is against the exact volume."""
    quiet = ("output.figures=false", "output.uncertainty=false", "output.resolvability=false")  # none of what it checks
    runs = {n: run(_cfg(f"resolution={n}", "n_dips=30", *quiet), tmp_path / str(n)) for n in (16, 24)}
    exact = 121969.935  # (2a)^3 - a^3 - 0.045 a^3 for the built-in radius 45 mm, a = 45 / sqrt(3)
    for n, result in runs.items():
        assert result.measurement.volume_estimate() == pytest.approx(exact, rel=1e-3)
        grid_radius = result.reconstruction.grid.radius
        assert grid_radius == pytest.approx(45.0 / 0.9)  # object radius = fill x working ball
        recon_volume = result.metrics["reconstructed_volume_mm3"]
        assert result.metrics["volume_error"] == pytest.approx(recon_volume / exact - 1, rel=1e-3)
        assert abs(result.metrics["truth_voxel_volume_error"]) < 1e-6  # exact box occupancy
    assert runs[16].reconstruction.grid.extent != runs[24].reconstruction.grid.extent


def test_fixed_plan_under_the_authors_rig_stays_in_the_cap(tmp_path):
    result = run(reconstruct_cfg("resolution=16", "n_dips=12", "reach=authors_rig", "output.figures=false",
                                 "output.uncertainty=false"), tmp_path)
    tilt, _ = tilt_spin(result.measurement.directions)
    assert result.measurement.n_orientations == 12 and tilt.max() <= 35 + 1e-9


def test_metrics_count_the_measured_dips_apart_from_their_symmetry_images(tmp_path):
    """``n_dips`` counts the directions solved for (a declared symmetry's images too), ``n_dips_measured`` the
    dips actually measured (no field gave it)."""
    result = run(_cfg("resolution=16", "n_dips=10", "symmetry={n_fold:4}", "output.figures=false",
                      "output.uncertainty=false", "output.resolvability=false"), tmp_path)
    assert result.metrics["n_dips_measured"] == 10 and result.metrics["n_dips"] > 10


def test_an_empty_reconstruction_or_truth_mesh_is_not_written_and_the_log_says_why(tmp_path, caplog):
    """Before: reconstruction.ply / truth.ply were silently missing. An empty reconstruction's missing mesh is a line
    of the log (the job warned once, as the solve ended: test_an_empty_reconstruction_says_what_it_is_once)."""
    grid = Grid(12, 3, 200.0)
    cfg = OmegaConf.create({"output": {"mesh_formats": ["ply"], "figures": False}})
    with caplog.at_level("INFO", logger="dipnet.jobs.pipeline"):
        write_outputs(cfg, tmp_path, None, None, Reconstruction(torch.zeros(grid.shape), grid, 0.5),
                      np.full(grid.shape, 0.3))
    assert not list(tmp_path.iterdir())
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [
        ("WARNING", "the true shape has no surface on this grid (no voxel more than half inside), so truth.ply was "
                    "not written"),
        ("INFO", "the reconstruction is empty, so reconstruction.ply was not written")]


def test_an_empty_reconstruction_says_what_it_is_once(tmp_path, caplog):
    """Before: an empty result (a volume prior of weight 1e6, one step) logged "uncertainty is not calibrated on this
    run: error rate 1.000 in the most uncertain decile vs 1.000 in the least", a missing mesh, and "done: IoU 0.000,
    Chamfer 1.0000, ...": the Chamfer of an empty result is a stand-in (one truth diagonal), not a distance."""
    with caplog.at_level("INFO"):
        result = run(_cfg("resolution=16", "n_dips=12", "solver=voxel", "solver.priors.volume.weight=1e6",
                          "solver.iterations=1", "output.figures=false", "output.resolvability=false"), tmp_path)
    assert result.metrics["empty"] is True and result.metrics["chamfer"] == 1.0  # the stand-in stays in metrics.json
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "empty" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("the reconstruction is empty: no voxel of its occupancy reaches "
                                                     "its threshold 0.5 (the largest is "), warned
    assert "Chamfer and Hausdorff are 1.0 by convention (one truth diagonal, a stand-in" in warned[0]
    assert "not calibrated" not in caplog.text and "error_rate_by_uncertainty_decile" in result.metrics
    done = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("done: "))
    assert done.startswith("done: empty reconstruction, IoU 0.000, ") and "Chamfer" not in done, done


def test_the_outputs_bar_counts_to_the_stages_the_job_runs(tmp_path, monkeypatch):
    """The bar went from 5/6 to "100% 5/5": its total was every stage until one was skipped."""
    from dipnet.outputs import progress
    from progress_bars import RecordingBar

    class FirstTotal(RecordingBar):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.first_total = self.total

    RecordingBar.made = []
    monkeypatch.setattr(progress, "tqdm", FirstTotal)
    run(_cfg("ndim=2", "resolution=32", "n_dips=10", "output.figures=false", "output.progress=true"), tmp_path)
    (bar,) = RecordingBar.made
    assert bar.first_total == bar.n == bar.total < len(progress.STAGES)


def test_a_run_into_the_folder_of_an_earlier_run_names_the_files_it_did_not_write(tmp_path, cli):
    """Before: a recording reconstructed into the hydra.run.dir of a simulated run left that run's truth.ply,
    truth.stl, reconstruction.stl (the other object's) and 6 figures beside its own results, exit 0 without a word.
    The same command again writes every file again: no warning; the recording it reads is not named."""
    quick = ["resolution=16", "output.figures=false", "output.uncertainty=false", "output.resolvability=false"]
    assert cli(tmp_path, *quick, "n_dips=8", "output.mesh_formats=[ply,stl]").returncode == 0
    again = cli(tmp_path, *quick, "n_dips=8", "output.mesh_formats=[ply,stl]")
    assert again.returncode == 0 and "earlier run" not in again.stderr + (tmp_path / "reconstruct.log").read_text()
    extent = float(np.load(tmp_path / "reconstruction.npz")["grid_extent"])
    recorded = cli(tmp_path, *quick, "source=recorded", f"source.reader.path={tmp_path / 'rawscan.jsonl'}",
                   f"extent_mm={extent}", "n_slabs=${resolution}")
    assert recorded.returncode == 0, recorded.stderr[-2000:]
    assert (f"{tmp_path} holds 3 file(s) of an earlier run that this run did not write: reconstruction.stl, "
            "truth.ply, truth.stl; they are not this run's results: delete them, or give each run its own "
            "hydra.run.dir") in (tmp_path / "reconstruct.log").read_text()
    # whose numbers metrics.json holds: the overrides of the run that wrote it, as Hydra saved them for that run
    # (compare.py tells a later run's refusal from the earlier run's metrics by them)
    # (as typed: an interpolation unresolved, as Hydra saves it; resolved, this run's own metrics were "an earlier
    # run's", unfinished)
    from dipnet.experiments import collect

    written = json.loads((tmp_path / "metrics.json").read_text())["overrides"]
    assert written == OmegaConf.to_container(OmegaConf.load(tmp_path / ".hydra" / "overrides.yaml"), resolve=False)
    assert "source=recorded" in written and "n_slabs=${resolution}" in written
    assert json.loads((tmp_path / "metrics.json").read_text())["solver_config"] == "minnorm"  # conf/solver/<this>.yaml
    assert collect.load_run(tmp_path).status == "ok"


def test_the_mesh_comes_from_the_solvers_finer_sampling_when_it_made_one(tmp_path, caplog):
    """Before: ``solver=implicit solver.output_upsample=2`` sampled the field at 2N and the job dropped it without a
    word: reconstruction.ply was the N^3 surface, as without the option (a ball of radius 30 mm: 102,214 mm^3 at
    8^3 for 113,097; 110,677 at 32^3). Now the mesh is the fine one."""
    coarse, fine = Grid(8, 3, 100.0), Grid(32, 3, 100.0)

    def ball(grid):
        return torch.as_tensor((grid.centers().norm(dim=-1) <= 30.0).double())

    recon = Reconstruction(ball(coarse), coarse, 0.5)
    recon.fine = Reconstruction(ball(fine), fine, 0.5)
    cfg = OmegaConf.create({"output": {"mesh_formats": ["ply"], "figures": False}})
    with caplog.at_level("INFO", logger="dipnet.jobs.pipeline"):
        write_outputs(cfg, tmp_path, None, None, recon, None)
    import trimesh

    from dipnet.shapes.isosurface import volume_to_mesh

    mesh = trimesh.load(tmp_path / "reconstruction.ply", force="mesh")
    assert mesh.volume == pytest.approx(volume_to_mesh(recon.fine.occupancy, fine, 0.5).volume, rel=1e-9)
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 30.0**3, rel=0.03)
    assert "the reconstruction's mesh is its field sampled at 32^3" in caplog.text


def test_the_uncertainty_calibration_scores_the_truth_that_iou_scores(tmp_path):
    """The audit's case: the job scored ``error_rate_by_uncertainty_decile`` and ``uncertainty_brier`` against the true
    occupancy above 0.5, while IoU and the false rates score it above ``truth_level``, the level whose voxels hold the
    exact volume (a 0.5 cut is 15 % too large for the chamber box at 24^3: 219 wrong voxels instead of 125, Brier
    0.060 instead of 0.044, the top decile's error rate 0.337 instead of 0.266). Now both score one reference."""
    from dipnet.evaluation.uncertainty import calibration_by_decile
    from dipnet.shapes import builtin_shape

    result = run(reconstruct_cfg("resolution=24", "n_dips=12", "output.figures=false"), tmp_path)
    metrics = result.metrics
    grid = result.reconstruction.grid
    truth = builtin_shape("chamber_box", 3, 45.0).occupancy(grid, supersample=3).numpy()
    with np.load(tmp_path / "reconstruction.npz") as saved:
        p_wrong, binary = saved["uncertainty_p_wrong"], saved["binary"]
    reference = truth > metrics["truth_level"]
    assert metrics["truth_level"] != 0.5 and (reference != (truth > 0.5)).sum() > 0
    assert metrics["error_rate_by_uncertainty_decile"] == [
        round(float(v), 5) for v in calibration_by_decile(p_wrong, binary, reference)]
    assert (binary & ~reference).sum() / reference.sum() == pytest.approx(metrics["false_positive"])


def test_a_measurement_read_from_the_run_folder_it_would_be_replaced_in_is_refused(tmp_path, cli):
    """Before: a run's measurement.npz re-solved into the same folder at 16 slabs replaced the file with its re-binned
    copy, without a word; a later run at 32 slabs solved that copy (IoU 0.932 -> 0.641) and said ``consistent``.
    Now the run is refused before anything is written, and the recording stays as it was."""
    quick = ["output.figures=false", "output.uncertainty=false", "output.resolvability=false"]
    assert cli(tmp_path, *quick, "resolution=24", "n_dips=8").returncode == 0
    recording = tmp_path / "measurement.npz"
    before = recording.read_bytes()
    again = cli(tmp_path, *quick, "resolution=16", "source=recorded", f"source.reader.path={recording}")
    assert again.returncode == 2 and "Traceback" not in again.stderr
    assert "lies in this run's output folder" in again.stderr and "another hydra.run.dir" in again.stderr
    assert recording.read_bytes() == before
    elsewhere = cli(tmp_path / "elsewhere", *quick, "resolution=16", "source=recorded",
                    f"source.reader.path={recording}")
    assert elsewhere.returncode == 0 and recording.read_bytes() == before


def test_mesh_files_of_a_scaled_mesh_map_back_onto_the_users_file(tmp_path):
    """``shape.radius`` scales the user's mesh: metrics.json states the factor (``frame_scale``, mm per unit of
    the file) beside the shift, and the written meshes divided by it lie on the file's mesh within a voxel."""
    corners = [[x, y, z] for x in (0, 40) for y in (0, 20) for z in (0, 10)] + [[45, 25, 30]]  # no symmetry
    source = trimesh.convex.convex_hull(np.array(corners, float)).apply_translation([100.0, -50.0, 20.0])
    source.export(tmp_path / "part.stl")
    run(_cfg("shape=mesh", f"shape.path={tmp_path / 'part.stl'}", "shape.radius=45", "resolution=16", "n_dips=24",
             "output.figures=false", "output.uncertainty=false", "output.resolvability=false"), tmp_path / "job")
    saved = json.loads((tmp_path / "job" / "metrics.json").read_text())
    scale = saved["frame_scale"]
    assert 45.0 / scale == pytest.approx(np.linalg.norm(source.vertices - source.center_mass, axis=1).max())
    voxel = float(np.load(tmp_path / "job" / "reconstruction.npz")["grid_extent"]) / 16 / scale   # in file units
    for name in ("truth.ply", "reconstruction.ply"):
        mesh = trimesh.load(tmp_path / "job" / name)
        back = mesh.copy().apply_scale(1.0 / scale)
        np.testing.assert_allclose(back.bounds, source.bounds, atol=1.5 * voxel, err_msg=name)
        assert back.volume == pytest.approx(mesh.volume / scale**3)


def test_a_rerun_from_the_measurement_of_a_mesh_job_writes_its_mesh_in_the_same_frame(tmp_path):
    """A mesh job's ``measurement.npz`` keeps the frame of the user's file: read back (``source=recorded``), its
    reconstruction lies where the first run's did (it was 97 mm away, centred), and metrics.json says so again."""
    trimesh.creation.box(extents=(30.0, 20.0, 16.0)).apply_translation([40.0, -25.0, 12.0]).export(tmp_path / "p.stl")
    quiet = ("resolution=16", "output.figures=false", "output.uncertainty=false", "output.resolvability=false")
    first = run(_cfg("shape=mesh", f"shape.path={tmp_path / 'p.stl'}", "shape.scale=2", "n_dips=24", *quiet),
                tmp_path / "first")
    again = run(_cfg("source=recorded", f"source.reader.path={tmp_path / 'first' / 'measurement.npz'}", *quiet),
                tmp_path / "again")
    for key in ("frame_offset_mm", "frame_scale"):
        assert again.metrics[key] == pytest.approx(first.metrics[key]), key
    assert first.metrics["frame_scale"] == 2.0
    np.testing.assert_allclose(trimesh.load(tmp_path / "again" / "reconstruction.ply").bounds,
                               trimesh.load(tmp_path / "first" / "reconstruction.ply").bounds, atol=1e-6)


def test_a_malformed_frame_in_a_measurements_metadata_is_left_out_with_a_warning(caplog):
    assert saved_frame({"frame_offset_mm": [1, 2, 3], "frame_scale": 2}) == {"frame_offset_mm": [1.0, 2.0, 3.0],
                                                                             "frame_scale": 2.0}
    assert saved_frame({"frame_offset_mm": [1, 2, float("nan")], "frame_scale": 3.5}) == {"frame_scale": 3.5}
    assert saved_frame({"frame_offset_mm": "abc", "frame_scale": -1}) == {}
    assert "frame_offset_mm='abc' is not three finite mm" in caplog.text and "frame_scale=-1" in caplog.text


def test_a_job_killed_while_writing_its_meshes_and_figures_is_not_called_finished(tmp_path, monkeypatch):
    """The audit's case: ``metrics.json`` was written before the meshes and figures, so a job killed between them
    (no mesh, no figure, no ``done:`` line) was tabled by ``compare.py`` as finished. It is now written last."""
    import dipnet.jobs.pipeline as pipeline
    from dipnet.experiments.collect import load_run

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # as a kill would stop it: nothing after this runs

    monkeypatch.setattr(pipeline, "write_outputs", killed)
    with pytest.raises(KeyboardInterrupt):
        run(_cfg("resolution=16", "n_dips=12", "output.uncertainty=false", "output.resolvability=false"), tmp_path)
    assert not (tmp_path / "metrics.json").exists() and load_run(tmp_path).status == "unfinished"


@pytest.mark.parametrize("overrides,match", [
    (["solver=voxel_learned", "resolution=16"], r"64\^3 grid"),
    (["solver=implicit_learned", "resolution=16"], r"64\^3 grid"),  # through its voxel_learned warm start too
    (["solver=voxel_learned", "ndim=2", "resolution=16"], "2D"),
    (["solver=voxel_learned", "resolution=64", "n_slabs=32"], "slabs"),
])
def test_a_grid_the_learned_weights_do_not_fit_is_refused_before_any_dip(tmp_path, overrides, match):
    # the refusal came after the dips were simulated (seconds to minutes) and measurement.npz / rawscan.jsonl written
    with pytest.raises(PriorMismatchError, match=match):
        run(_cfg(*overrides, "n_dips=8", "output.figures=false"), tmp_path)
    assert not (tmp_path / "measurement.npz").exists()
    assert not (tmp_path / "rawscan.jsonl").exists()
