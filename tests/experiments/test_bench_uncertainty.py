"""scripts/bench_uncertainty.py: its per-case scores on known answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from script_modules import load_script


def test_scores_of_a_perfect_and_of_a_blind_probability():
    bench = load_script("bench_uncertainty")
    truth = np.zeros((10, 10, 10), bool)
    truth[3:7, 3:7, 3:7] = True
    binary = truth.copy()
    binary[3, 3:7, 3:7] = False  # one wrong face
    perfect = bench.scores(truth.astype(float), (binary != truth).astype(float), binary, truth)
    assert perfect["brier"] == 0.0 and perfect["ece"] == 0.0 and perfect["top"] > 0 and perfect["deciles"][0] == 0
    blind = bench.scores(np.full(truth.shape, 0.5), np.full(truth.shape, 0.5), binary, truth)
    assert blind["brier"] == pytest.approx(0.25) and len(blind["deciles"]) == 10


def test_a_mesh_name_not_bundled_is_refused_before_any_case(capsys):
    """``--meshes torus nosuch``: a ``ShapeError`` traceback after the torus's whole case (15.7 s at 12^3, 8 dips,
    2 members); now refused by the argument parser, exit 2, naming it."""
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_uncertainty").parse_args(["--meshes", "torus", "nosuch"])
    assert exit_.value.code == 2
    assert "error: --meshes: no bundled mesh 'nosuch'; bundled: boot, " in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--samples", "1"],
     "--n 32, --dips 41, --samples 1, --iterations-scale 1: an ensemble needs n_samples >= 2, got 1"),
    (["--iterations-scale", "0"], "iterations_scale must be in (0, 1], got 0.0"),
    (["--iterations-scale", "2"], "iterations_scale must be in (0, 1], got 2.0"),
    (["--dips", "0"], "number of orientations must be a positive integer, got 0"),
    (["--n", "3"], "grid resolution n must be an integer >= 4, got 3"),
])
def test_bad_ensemble_options_are_refused_before_any_case(capsys, argv, message):
    """``--samples 1`` or ``--iterations-scale 0``: a ``ValueError`` traceback after the first case's reference solve
    and its linearised posterior; ``--dips 0``, ``--n 3`` tracebacks too. Now refused by the argument parser, exit 2."""
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_uncertainty").parse_args(["--meshes", "torus", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and message in err and err.count("error:") == 1, err


def test_the_learned_prior_runs_as_a_job_composes_it_on_its_grid():
    """``--solver prior`` is ``conf/solver/voxel_learned.yaml`` (the factory bench_quality.py uses), seeded as the
    bench asks, nested start included; ``--n`` defaults to the weights' 64 and the cases are the generated shapes and
    mesh files asked for (no bundled mesh with ``--meshes none``). No solve."""
    from dipnet.solvers.voxel import VoxelSolver

    bench = load_script("bench_uncertainty")
    args = bench.parse_args(["--solver", "prior", "--meshes", "none", "--generated", "2", "--generated-first", "2008"])
    assert args.n == 64 and bench.cases(args) == [("generated2008", 2008), ("generated2009", 2009)]
    assert bench.SOLVERS["prior"].config_name == "voxel_learned"
    prior = bench.SOLVERS[args.solver](progress=False, seed=5)
    assert isinstance(prior, VoxelSolver) and isinstance(prior.warm_start, VoxelSolver)
    assert prior.priors["learned"]["mode"] == "anchor"
    assert prior.later_priors["learned"]["weights"] == "denoiser64_stage2"
    assert prior.seed == 5 and prior.warm_start.seed == 5
    assert bench.parse_args([]).n == 32 and bench.parse_args(["--quick"]).n == 24  # the defaults keep their grids


@pytest.mark.parametrize("argv, message", [
    (["--solver", "prior", "--n", "32"], "--solver prior: its weights are for a 64^3 grid, not --n 32"),
    (["--meshes", "none"], "no case: --meshes none without --generated or --mesh-files"),
    (["--generated", "20", "--generated-first", "990"], "overlap the prior's training / validation seeds"),
    (["--mesh-files", "/nonexistent/cow.obj"], "--mesh-files: no file /nonexistent/cow.obj"),
])
def test_cases_the_learned_prior_cannot_run_are_refused_before_any_case(capsys, argv, message):
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_uncertainty").parse_args(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and message in err, err


@pytest.mark.parametrize("argv, message", [
    (["--snr", "nan"], "--snr: snr_db must be a number of dB in [-20, 200]"),
    (["--seed", "-1"], "--seed must be 0 or more, got -1"),
    (["--threads", "-1"], "--threads must be 1 or more, got -1"),
    (["--threads", "0"], "--threads must be 1 or more, got 0"),
    (["--json", "/nonexistent/dir/rows.json"], "--json /nonexistent/dir/rows.json: no folder /nonexistent/dir"),
    (["--mesh-files", "{readme}"], "--mesh-files: cannot read mesh file"),
])
def test_run_options_that_fail_later_are_refused_before_any_case(capsys, argv, message):
    """``--solver prior --snr nan``: a traceback at the first 30 dB case, after the noise-free one (minutes at 64^3);
    ``--seed -1``, ``--threads -1`` and a ``--mesh-files`` file that is no mesh: tracebacks; ``--threads 0`` was
    ignored unsaid; ``--json`` in a missing folder: a traceback after every case. Now refused by the argument parser,
    exit 2."""
    readme = Path(__file__).parents[2] / "README.md"
    argv = [a.format(readme=readme) for a in argv]
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_uncertainty").parse_args(["--solver", "prior", "--meshes", "torus", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and message in err and err.count("error:") == 1, err


def test_the_quick_mode_of_the_learned_prior_keeps_its_weights_grid():
    """``--quick --solver prior`` was refused as ``not --n 24``, an --n never given: the quick mode's grid is not one
    the prior's weights can run; it keeps their 64^3 and the quick cases."""
    args = load_script("bench_uncertainty").parse_args(["--quick", "--solver", "prior"])
    assert args.n == 64 and args.meshes == ["bunny", "torus"] and args.noise == ["clean"]
