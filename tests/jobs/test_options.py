"""Issue 22, options: every option of scripts/reconstruct.py is checked before any work (one line
``error: ...`` naming the option, exit 2, no result written), options no code reads are refused,
every preset takes every solver, and Ctrl-C / an unwritable run directory end in one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.jobs.options import ConfigError, check_config
from script_runs import one_line_error

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "reconstruct.py"
CONF = Path(__file__).resolve().parents[2] / "conf"
SMALL = ("output.progress=false", "output.figures=false", "output.uncertainty=false", "output.resolvability=false",
         "resolution=16")
RECORDED = ("source=recorded", f"source.reader.path={CATS_CSV}")


def _cli(run_dir: Path, *overrides: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), f"hydra.run.dir={run_dir}", *SMALL, *overrides],
                          capture_output=True, text=True, timeout=300, env=env)


@pytest.mark.parametrize("overrides,message", [
    (["snr_db=abc"], "error: snr_db must be a number of dB in [-20, 200] or null (noise-free), got 'abc'"),
    (["resolution=abc"], "error: resolution must be an integer >= 4 (voxels per axis), got 'abc'"),
    (["seed=-1"], "error: seed must be an integer >= 0 and below 4294967296, got -1"),
    (["+n_dip=40"], "error: unknown option n_dip: no code reads it; did you mean n_dips?"),
    (["+operator.bogus_option=1"], "error: unknown option operator.bogus_option: make_operator takes "),
    (["+solver.tikhonovv=0.2"], "error: unknown option solver.tikhonovv: MinNormSolver takes "),
    (["+output.figure=false"], "error: unknown option output.figure: no code reads it; did you mean output.figures?"),
    ([*RECORDED, "+source.reader.smoth=false"], "error: unknown option source.reader.smoth: read_recorded takes "),
    ([*RECORDED, "planner=adaptive"], "error: planner=adaptive is ignored with source=recorded"),
    ([*RECORDED, "n_dips=40"], "error: option n_dips is ignored with source=recorded"),
    ([*RECORDED, "snr_db=20"], "error: option snr_db is ignored with source=recorded"),
    ([*RECORDED, "reach=authors_rig"], "error: option reach is ignored with source=recorded"),
    (["planner=adaptive", "orientations=random"], "error: option orientations is ignored with planner=adaptive"),
    (["+source.simulator.sensor.seed=5"], "error: option source.simulator.sensor.seed is ignored with "
     "source=simulated (the job's seed sets the simulated noise: give seed=... instead): remove it"),  # was ignored
    (["output.mesh_formats=[xyz]"], "error: output.mesh_formats must be a list of ply, stl, obj, got ['xyz']"),
    (["output.checkpoint_every=0"], "error: output.checkpoint_every must be a positive integer, got 0"),
    (["calibration=self", "solver=voxel", "calibration.iterations=0"],
     "error: calibration.iterations must be a positive integer (rounds of the joint shape + cross-section step), "
     "got 0"),
])
@pytest.mark.slow
def test_bad_options_are_refused_before_any_work(tmp_path, overrides, message):
    line = one_line_error(_cli(tmp_path, *overrides))
    assert line.startswith(message), line
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "measurement.npz").exists()


@pytest.mark.slow
def test_a_rejected_run_leaves_what_the_guide_says(tmp_path):
    """docs/guide/bad-data.md: Hydra's config and log (the error logged once) and the empty run-directory lock."""
    one_line_error(_cli(tmp_path, "n_dips=-5"))
    assert sorted(p.name for p in tmp_path.iterdir()) == [".dipnet-run.lock", ".hydra", "reconstruct.log"]
    log = (tmp_path / "reconstruct.log").read_text()
    assert log.count("error: n_dips must be a positive integer, got -5") == 1, log


@pytest.mark.slow
def test_report_without_plotly_is_refused_before_any_work(tmp_path):
    fake = tmp_path / "site" / "plotly"  # an environment without the `report` extra
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('No module named plotly')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(fake.parent), os.environ.get("PYTHONPATH")]))}
    line = one_line_error(_cli(tmp_path / "run", "output.report=true", env=env))
    assert line.startswith("error: output.report=true: HTML reports need plotly: pip install"), line
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.slow
def test_unwritable_run_directory_is_named(tmp_path):
    (tmp_path / "reconstruct.log").mkdir()  # the log file cannot be written (root ignores chmod)
    line = one_line_error(_cli(tmp_path))
    assert line.startswith(f"error: the run directory {tmp_path} is not writable"), line
    assert "hydra.run.dir" in line


@pytest.mark.slow
def test_ctrl_c_during_a_solve_says_how_to_resume(tmp_path):
    proc = subprocess.Popen([sys.executable, str(SCRIPT), f"hydra.run.dir={tmp_path}", *SMALL, "n_dips=12",
                             "solver=voxel", "solver.iterations=100000", "solver.tol=0", "output.checkpoint=true"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # the job runs as in a terminal's foreground: a shell starts `cmd &` with SIGINT ignored, the
    # job inherits that and Python then never raises KeyboardInterrupt (CI launched that way hung here)
    for line in proc.stdout:  # Hydra logs to stdout: wait until the solve has started
        if "checkpointing the solve" in line:
            break
    proc.send_signal(signal.SIGINT)
    try:
        _, stderr = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:  # fail with what the job said, not a bare timeout
        proc.kill()
        _, stderr = proc.communicate()
        pytest.fail(f"Ctrl-C did not end the job within 120 s; its stderr ends:\n{stderr[-3000:]}")
    line = one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, "", stderr), code=130,
                           prefix="interrupted: ")
    assert f"rerun the same command with hydra.run.dir={tmp_path} to resume" in line, line


@pytest.mark.parametrize("override,message", [
    ("snr_db=1e308", r"snr_db must be a number of dB in \[-20, 200\] or null \(noise-free\), got 1e\+308"),
    ("snr_db=-300", r"snr_db must be a number of dB in \[-20, 200\].*got -300"),
    ("source.simulator.smooth=maybe", "source.simulator.smooth must be true or false, got 'maybe'"),
    # a string is true to Python: output.figures=no drew every figure, output.report=no wrote report.html, exit 0
    ("output.figures=no", "output.figures must be true or false, got 'no'"),
    ("output.report=no", "output.report must be true or false, got 'no'"),
    ("output.resolvability=off", "output.resolvability must be true or false, got 'off'"),
    ("output.progress=no", "output.progress must be true or false, got 'no'"),
    ("operator=fourier operator.single=no", "operator.single must be true or false, got 'no'"),
    # upsampfac=nan crashed the job in finufft (segmentation fault) after the dips were simulated; 1 or less ended
    # in finufft's "opts.upsampfac not > 1.0", naming no option
    ("operator=fourier operator.upsampfac=nan", r"operator.upsampfac \(the NUFFT's oversampling factor\) must be "
                                                r"null \(finufft's choice\) or a number in \[1.15, 3\].*got nan"),
    ("operator=fourier operator.upsampfac=1", r"operator.upsampfac .*got 1$"),
    ("operator=fourier operator.eps=0.1", r"operator.eps \(the NUFFT's relative tolerance\) must lie in \(0, 0.01\]"),
    ("operator=fourier +operator.nthreads=-1", r"operator.nthreads .* must be a whole number >= 1, got -1"),
    ("shape=mesh shape.path=m.ply shape.fill_sealed_voids=no", "shape.fill_sealed_voids must be true or false"),
    ("solver.threshold=2.0", r"solver.threshold must be an occupancy level in \(0, 1\) or the solver's rule "
                             r"\(otsu, volume\), got 2.0"),
    ("solver.threshold=0", r"solver.threshold must be an occupancy level in \(0, 1\).*got 0"),
    ("solver=implicit_learned solver.warm_start.threshold=-1", r"solver.warm_start.threshold must be .*got -1"),
    # a NaN weight ran, and ended as "the loss became nan ... try a lower solver.lr"
    ("solver=voxel solver.priors.tv.weight=nan", r"solver.priors.tv.weight: prior 'tv' has weight nan: a weight is a "
                                                 r"finite number >= 0 \(0 = off\) or 'auto'"),
    ("solver=implicit solver.priors.l1.weight=-2", r"solver.priors.l1.weight: prior 'l1' has a negative weight -2.0"),
    ("symmetry={n_fold:3,mirror:maybe}", "symmetry.mirror must be true or false, got 'maybe'"),
    ("symmetry={n_fold:2.5}", r"symmetry.n_fold must be a positive integer \(rotations about z\), got 2.5"),
    ("symmetry={n_fold:3,mirorr:true}", "unknown option symmetry.mirorr: .*did you mean symmetry.mirror"),
    ("symmetry={tol_deg:-1}", r"symmetry.tol_deg must be a number >= 0 \(deg\), got -1"),
    # a symmetry that adds no image ran, exit 0, as without it; a mirror azimuth without a mirror was ignored
    ("symmetry={}", r"symmetry=\{\} declares no symmetry \(n_fold 1 without a mirror: the identity\)"),
    ("symmetry={n_fold:1,tol_deg:1}", r"symmetry=\{'n_fold': 1, 'tol_deg': 1\} declares no symmetry"),
    ("symmetry={mirror_azimuth_deg:30}", r"option symmetry.mirror_azimuth_deg is ignored with symmetry.mirror=false "
                                         r"\(it places the mirror plane, deg\): add mirror: true"),
    ("symmetry={n_fold:3,mirror:false,mirror_azimuth_deg:30}", "symmetry.mirror_azimuth_deg is ignored"),
    ("symmetry={n_fold:4,tol_deg:15}", r"symmetry.tol_deg must be at most 2 \(deg\), got 15: .*distinct dips"),
    # 2D: refused after the dips were simulated ("symmetry expansion is for 3D measurements", no fix named)
    ("ndim=2 symmetry={n_fold:4,mirror:true}", r"symmetry=\{'n_fold': 4, 'mirror': True\} copies 3D dips .* set "
                                               r"symmetry=null with ndim=2; .*solver.priors.symmetry"),
    # 2D: "dip 0 has no rig angles" (voxel), or a cross-section step that needs another solver (minnorm)
    ("ndim=2 calibration=self", r"calibration=self fits the 3D rig's geometry .* set ndim=3, or drop calibration"),
    ("calibration=self calibration.dip_offset_sigma_mm=-1",
     r"calibration.dip_offset_sigma_mm must be a positive number or null \(mm, .*got -1"),
    ("calibration=self calibration.iterations=0", "calibration.iterations must be a positive integer .*got 0"),
    ("calibration=self calibration.max_section_change=0", "calibration.max_section_change must be a positive number"),
    ("calibration=self calibration.max_section_change=20",
     r"calibration.max_section_change must be a fraction in \(0, 1\) or null .*got 20 \(20 would accept any section"),
    ("solver=implicit solver.hidden_width=0",
     r"solver.hidden_width must be a positive integer \(neurons per hidden layer\), got 0"),
    ("solver=implicit solver.hidden_layers=-1", "solver.hidden_layers must be an integer >= 0 .*got -1"),
    ("solver=implicit solver.encoding.levels=0", "solver.encoding.levels must be a positive integer .*got 0"),
    ("solver=implicit ~solver.encoding +solver.encoding={type:positional,n_frequencies:0}",
     "solver.encoding.n_frequencies must be a positive integer .*got 0"),
    ("solver=voxel solver.iterations=2.5", "solver.iterations must be a positive integer .*got 2.5"),
    ("solver=implicit_learned solver.warm_start.iterations=0", "solver.warm_start.iterations must be a positive"),
    ("shape=generated shape.mesh_resolution=2",
     r"shape.mesh_resolution must be an integer >= 16 \(marching-cubes cells per axis\), got 2"),
    ("shape=generated shape.seed=-3", r"shape.seed must be an integer >= 0 \(which solid\), got -3"),
    # 2 slabs left no noise estimate: the residual limit was null and the residual check passed unsaid
    ("n_slabs=2", r"n_slabs must be an integer >= 3 or null \(slabs per profile: .*got 2"),
    # 1000 sampled a ball's truth at 1e9 points per voxel and never ended (a box's exact occupancy ignored it)
    ("output.truth_supersample=1000", r"output.truth_supersample must be a positive integer and below 17 \(sub-voxel "
                                      r"samples per axis .*got 1000"),
])
def test_out_of_range_values_are_refused_by_check_config(override, message):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=override.split())
    with pytest.raises(ConfigError, match=message):
        check_config(cfg)



@pytest.mark.parametrize("overrides,message,fine", [
    # a reach is the 3D rig's tilt and spin: in 2D it was ignored (directions over 0-180 deg, exit 0)
    (["ndim=2", "reach=authors_rig"], r"option reach is ignored with ndim=2 \(a reach is the 3D rig's tilt",
     ["ndim=2"]),  # the default reach (not typed) is fine
    # a 2D job writes no mesh: output.mesh_formats=[stl] wrote nothing, exit 0, without a word
    (["ndim=2", "output.mesh_formats=[stl]"], r"option output.mesh_formats is ignored with ndim=2 \(.*writes no mesh",
     ["ndim=2", "output.figures=false", "output.mesh_formats=[]"]),  # no mesh asked for (paper_figures.py's jobs)
    # shape.axis picks the 2D silhouette of a mesh: with ndim=3 it was ignored, exit 0, without a word
    (["shape=mesh", "shape.path=m.ply", "shape.axis=x"], r"option shape.axis is ignored with ndim=3 \(.*2D silhouette",
     ["shape=mesh", "shape.path=m.ply", "shape.axis=x", "ndim=2"]),
    # fill sizes the grid only when extent_mm is null: extent_mm=150 fill=0.3 ran the extent_mm=150 job, exit 0
    (["extent_mm=150", "fill=0.3"], r"option fill is ignored with extent_mm set \(fill chooses the grid's side",
     ["fill=0.3"]),  # with extent_mm=null (the default), fill sizes the grid
    # iter_lim bounds LSMR / LSQR only: solver.method=cholesky solver.iter_lim=5 ran the direct solve, exit 0
    (["solver=minnorm", "solver.method=cholesky", "solver.iter_lim=5"],
     r"option solver.iter_lim is ignored with solver.method=cholesky \(iter_lim bounds the iterative methods",
     ["solver=minnorm", "solver.method=lsmr", "solver.iter_lim=5"]),
    # the ensemble's size and iterations: with the default (linearised) uncertainty they ran nothing, exit 0
    (["output.uncertainty_samples=8"],
     r"option output.uncertainty_samples is ignored with output.uncertainty other than samples \(they size the",
     ["output.uncertainty=samples", "output.uncertainty_samples=8"]),
    (["output.uncertainty=false", "output.uncertainty_iterations=0.2"],
     r"option output.uncertainty_iterations is ignored with output.uncertainty other than samples",
     ["output.uncertainty=samples", "output.uncertainty_iterations=0.2"]),
    # a recording has no ground truth to supersample: output.truth_supersample=5 ran, exit 0, no word
    ([*RECORDED, "output.truth_supersample=5"], "option output.truth_supersample is ignored with source=recorded",
     ["output.truth_supersample=5"]),
    # checkpoint_every without a checkpoint: the solve ran unsaved, exit 0, no word (a killed run restarted from 0)
    (["solver=voxel", "output.checkpoint_every=5"],
     r"option output.checkpoint_every is ignored with output.checkpoint=null \(it sets how often",
     ["solver=voxel", "output.checkpoint=true", "output.checkpoint_every=5"]),
])
def test_an_option_the_dimension_ignores_is_refused(overrides, message, fine):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
        check_config(compose(config_name="config", overrides=fine), fine, ["reach", "shape"])
    with pytest.raises(ConfigError, match=message):
        check_config(cfg, overrides, ["reach", "shape"])


@pytest.mark.parametrize("option", ["source.reader.calibration=cal.yaml", "source.reader.smooth=true",
                                    "+source.reader.cross_section_mm2=600", "source.reader.geometry.pivot_mm=20",
                                    "source.reader.truncated=keep"])
def test_a_raw_reader_option_given_with_an_npz_measurement_is_refused(option):
    """A ``.npz`` holds profiles already made from readings: ``source.reader.calibration=cal.yaml`` (a rig
    calibration), a smoothing, a tank section or a rig geometry given with one were ignored, exit 0, without a
    word (the result that of the file's own geometry). The same options with a raw scan, and a preset's values
    (not typed), stay fine."""
    npz = ["source=recorded", "source.reader.path=run/measurement.npz"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*npz, option])
        raw = ["source=recorded", "source.reader.path=scan.jsonl", option]
        check_config(compose(config_name="config", overrides=raw), raw, ["source"])
        preset = ["experiment=cats_real", "source.reader.path=run/measurement.npz"]
        check_config(compose(config_name="config", overrides=preset), preset, ["source", "experiment"])
    key = option.lstrip("+").split("=")[0]
    with pytest.raises(ConfigError, match=rf"option {key} is ignored with an .npz source.reader.path \(a "
                                          r"measurement file holds slab profiles already made from readings"):
        check_config(cfg, [*npz, option], ["source"])


def test_a_typed_posterior_grid_finer_than_the_job_is_refused_and_a_default_one_is_not():
    """planner=adaptive planner.planner.resolution=1000 ran the posterior at the job's resolution 16, unsaid."""
    typed = ["planner=adaptive", "resolution=16", "planner.planner.resolution=1000"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=typed)
        default = ["planner=adaptive", "resolution=16"]  # its posterior grid, 32, is capped as documented
        check_config(compose(config_name="config", overrides=default), default, ["planner"])
        check_config(compose(config_name="config", overrides=typed[:2] + ["planner.planner.resolution=16"]),
                     typed[:2] + ["planner.planner.resolution=16"], ["planner"])
    with pytest.raises(ConfigError, match=r"^planner.planner.resolution=1000 is above the job's resolution=16: the "
                                          r"planner's posterior grid is at most the reconstruction's .*give "
                                          r"planner.planner.resolution <= 16"):
        check_config(cfg, typed, ["planner"])


@pytest.mark.parametrize("overrides,says,not_about", [
    (["ndim=2", "output.mesh_formats=[stl]"], "writes no mesh", "reach"),
    (["ndim=2", "reach=authors_rig"], "tilt and spin range", "mesh"),
])
def test_a_2d_refusal_gives_the_reason_of_the_option_refused_only(overrides, says, not_about):
    # the refusal of output.mesh_formats with ndim=2 explained what a reach is, and the reach's what a 2D job writes
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    with pytest.raises(ConfigError, match=says) as refused:
        check_config(cfg, overrides, ["reach", "shape"])
    assert not_about not in str(refused.value).split("(", 1)[1]


@pytest.mark.parametrize("overrides", [["solver.threshold=0.3"], ["solver=voxel_learned"], ["solver=implicit_learned"],
                                       ["symmetry={n_fold:3,mirror:true,mirror_azimuth_deg:-30,tol_deg:0}"],
                                       ["calibration=self", "calibration.dip_offset_sigma_mm=0.5"],
                                       ["solver=implicit", "solver.hidden_layers=0"],
                                       ["shape=generated", "shape.seed=7", "shape.mesh_resolution=16"],
                                       ["solver=voxel", "solver.threshold=volume"],
                                       ["solver=implicit", "solver.threshold=volume"],
                                       ["solver=dip", "solver.threshold=0.4"]])
def test_occupancy_levels_and_named_threshold_rules_are_accepted(overrides):
    """The solvers guide's ``solver=voxel solver.threshold=volume`` (an option of every optimisation solver) was
    refused by Hydra ("Could not override 'solver.threshold' ... use +solver.threshold=volume", exit 2): the voxel,
    implicit and dip configs had no ``threshold``."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        check_config(compose(config_name="config", overrides=overrides))


@pytest.mark.parametrize("override,key,value",
                         [("source.reader.truncated=keep", "truncated", "keep"),
                          ("source.reader.calibration=rig_cal.yaml", "calibration", "rig_cal.yaml")])
def test_the_reader_options_the_messages_name_are_taken_as_written(override, key, value):
    """The reader's errors and the bad-data guide advise ``source.reader.truncated=keep`` and
    ``source.reader.calibration=FILE``; typed as given, Hydra refused both ("Could not override ... use +..."),
    exit 2: ``conf/source/recorded.yaml`` had neither key."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*RECORDED, override])
    check_config(cfg)
    assert cfg.source.reader[key] == value


# ----------------------------------------------------------------------------- presets x solvers
PRESETS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
SOLVERS = sorted(p.stem for p in (CONF / "solver").glob("*.yaml"))


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_takes_every_solver(preset, solver):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"experiment={preset}", f"solver={solver}"])
    check_config(cfg)
    built = instantiate(cfg.solver)
    assert built.name == solver or type(built).__name__.lower().startswith(solver[:3])


@pytest.mark.slow
def test_real_data_preset_solves_with_minnorm(tmp_path):
    proc = _cli(tmp_path, "experiment=cats_real", "solver=minnorm")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "metrics.json").is_file()
