"""The benchmark scripts' bookkeeping: the operator benchmark's reference time says whether it was
measured, and the simulation caches are keyed by the simulator's code version."""

from __future__ import annotations

import argparse
import json
import logging
import re

import numpy as np
import pytest
import torch

from dipnet.calibration.model import CalibrationReport
from dipnet.preprocessing.datasets import MESHES_DIR
from script_modules import SCRIPTS, load_script


@pytest.fixture(scope="module")
def bench_operator():
    return load_script("bench_operator")


def fourier_row(seconds: float) -> dict:
    return {"backend": "fourier", "n": 64, "k": 1000, "seconds": seconds, "forward_s": seconds / 2,
            "setup_s": 0.1, "peak_gb": 0.5, "rel_error": 1e-3}


def test_a_measured_reference_is_said_to_be_measured(bench_operator):
    rows = [{"backend": "rotate_sum", "n": 64, "k": 1000, "seconds": 40.0, "forward_s": 20.0, "setup_s": 0.0,
             "peak_gb": 1.0, "rel_error": 1e-2}, fourier_row(0.5)]
    assert bench_operator.result_line(rows).endswith("speedup_vs_rotate_sum=80 rotate_sum_time=measured")
    assert "| 80x |" in bench_operator._format_row(rows[1], rows)


def test_an_extrapolated_reference_is_said_to_be_extrapolated(bench_operator):
    rows = [{"backend": "rotate_sum", "n": 64, "k": 1000, "skipped": True, "estimate_s": 400.0}, fourier_row(0.5)]
    assert bench_operator.result_line(rows).endswith("speedup_vs_rotate_sum=800 rotate_sum_time=extrapolated")
    assert "800x vs extrapolated rotate_sum" in bench_operator._format_row(rows[1], rows)
    assert "skipped (extrapolated from K=" in bench_operator._format_row(rows[0], rows)
    assert bench_operator.result_line([fourier_row(0.5)]).endswith("speedup_vs_rotate_sum=nan rotate_sum_time=none")


def test_the_quality_cache_is_keyed_by_the_simulation_code(tmp_path, monkeypatch):
    """A second call with the same code reads the cache; after a (simulated) change to the simulator's
    sources it simulates afresh into new files."""
    bench = load_script("bench_quality")
    args = bench.parse_args(["--cache", str(tmp_path), "--n", "8"])
    grid = bench.Grid(8)
    bench.case_data(args, MESHES_DIR / "torus.ply", grid, 3, "clean")
    first = sorted(p.name for p in tmp_path.iterdir())
    assert len(first) == 2 and all(f"_code{bench.simulation_digest()}" in name for name in first)
    bench.case_data(args, MESHES_DIR / "torus.ply", grid, 3, "clean")
    assert sorted(p.name for p in tmp_path.iterdir()) == first  # cached
    monkeypatch.setattr(bench, "simulation_digest", lambda: "0123456789ab")
    bench.case_data(args, MESHES_DIR / "torus.ply", grid, 3, "clean")
    assert len(list(tmp_path.glob("*_code0123456789ab*"))) == 2


def test_the_scale_cache_is_keyed_by_the_simulation_code(tmp_path, monkeypatch):
    bench = load_script("bench_scale")
    args = argparse.Namespace(cache=tmp_path, fill=0.9, noise=["clean"], snr=30.0)
    grid = bench.Grid(8)
    shape = bench.load_mesh(MESHES_DIR / "torus.ply", radius=0.9 * grid.radius)
    _, seconds = bench.simulate(args, shape, grid, 3)
    assert seconds > 0 and [p.name for p in tmp_path.iterdir()][0].count(f"_code{bench.simulation_digest()}") == 1
    assert bench.simulate(args, shape, grid, 3)[1] == 0.0  # cached
    monkeypatch.setattr(bench, "simulation_digest", lambda: "0123456789ab")
    assert bench.simulate(args, shape, grid, 3)[1] > 0  # the code changed: simulated again


def test_the_prior_headline_ratios_and_result_line(capsys):
    """Per-mesh ratios of prior at the small budget over minnorm at the large one, the noisy worst
    case and the share of generated shapes where prior beats voxel, from hand-made rows."""
    bench = load_script("bench_quality")
    args = bench.parse_args(["--headline", "--quick"])
    assert (args.n, args.budgets, args.generated, args.meshes) == (64, [41, 410], 2, ["bunny"])
    assert args.plan == {"minnorm": [410], "voxel": [41], "prior": [41]}

    def row(mesh, kind, dips, noise, solver, chamfer):
        return {"mesh": mesh, "set": kind, "dips": dips, "noise": noise, "solver": solver, "chamfer": chamfer,
                "seconds": 1.0}
    rows = [row("a", "mesh", 410, "clean", "minnorm", 0.002), row("a", "mesh", 41, "clean", "prior", 0.001),
            row("b", "mesh", 410, "clean", "minnorm", 0.002), row("b", "mesh", 41, "clean", "prior", 0.003),
            row("c", "mesh", 410, "clean", "minnorm", 0.004), row("c", "mesh", 41, "clean", "prior", 0.003),
            row("a", "mesh", 410, "snr", "minnorm", 0.002), row("a", "mesh", 41, "snr", "prior", 0.0025),
            row("g1", "generated", 41, "clean", "voxel", 0.002), row("g1", "generated", 41, "clean", "prior", 0.001),
            row("g2", "generated", 41, "clean", "voxel", 0.002), row("g2", "generated", 41, "clean", "prior", 0.003)]
    assert bench.prior_ratios(rows, 41, 410, "clean") == {"a": 0.5, "b": 1.5, "c": 0.75}
    bench.print_prior_summary(rows, 41, 410)
    assert capsys.readouterr().out.strip().splitlines()[-1] == (
        "RESULT prior41_over_minnorm410_median=0.750 prior41_over_minnorm410_worst=1.500 snr_worst=1.250 "
        "beats_voxel_generated=0.500")


def test_the_quality_bench_runs_each_solver_at_its_own_budgets():
    bench = load_script("bench_quality")
    assert bench.parse_args(["--dips", "voxel=41", "minnorm=123,410"]).plan == {"voxel": [41], "minnorm": [123, 410]}
    assert bench.parse_args(["--budgets", "41", "--solvers", "voxel"]).plan == {"voxel": [41]}
    with pytest.raises(ValueError, match="--dips expects SOLVER=K"):
        bench.parse_args(["--dips", "voxel=many"])
    rows = [{"noise": "clean", "mesh": "a", "dips": 41, "solver": "voxel", "chamfer": 0.003},
            {"noise": "clean", "mesh": "a", "dips": 410, "solver": "minnorm", "chamfer": 0.002},
            {"noise": "clean", "mesh": "b", "dips": 41, "solver": "voxel", "chamfer": 0.001}]
    assert bench.mesh_ratios(rows) == {"clean": {"a": pytest.approx(1.5)}}  # b has no minnorm row


def test_the_quality_bench_runs_the_learned_prior_as_a_job_would():
    """``prior`` is ``conf/solver/voxel_learned.yaml`` (voxel solve, then a refit anchored to D of
    it), not a second recipe written in the script; ``--options`` merge into that config."""
    from dipnet.solvers.voxel import VoxelSolver

    bench = load_script("bench_quality")
    prior = bench.SOLVERS["prior"]()
    assert isinstance(prior, VoxelSolver) and isinstance(prior.warm_start, VoxelSolver)
    assert not prior.coarse_to_fine and prior.temperature_start == prior.temperature_end and prior.rounds > 1
    assert prior.priors["learned"]["mode"] == "anchor" and prior.priors["learned"]["weight"] == "auto"
    assert prior.later_priors["learned"]["weights"] == "denoiser64_stage2" and prior.min_rounds == 3  # the cascade
    assert prior.weight_rule.tau == 0.8 and prior.weight_rule.largest == 16.0  # the anchor's weight follows the noise
    assert prior.threshold == "volume" and prior.warm_start.threshold == 0.5  # the measured volume sets the level
    assert bench.SOLVERS["prior"](priors={"learned": {"weight": 3.0}}).priors["learned"]["weight"] == 3.0
    implicit = bench.SOLVERS["implicit_prior"]()  # the field starts from voxel_learned's whole recipe
    start = implicit.warm_start
    assert isinstance(start, VoxelSolver) and start.priors["learned"] == prior.priors["learned"]
    assert isinstance(start.warm_start, VoxelSolver) and implicit.priors["learned"]["mode"] == "anchor"
    assert implicit.priors["learned"]["weights"] == "denoiser64_stage2"  # its start is a cascade result
    assert implicit.threshold == "volume" and start.threshold == 0.5  # pre-fitted to the start's occupancy as it is
    assert prior.surface_refit is not None and implicit.surface_refit == prior.surface_refit  # both refit their surface
    assert start.surface_refit is None  # the field's start is not refitted: the field's result is


def test_the_truth_row_scores_the_truths_own_occupancy(tmp_path, capsys):
    """``--solvers truth`` solves nothing: its row is the partial-volume truth, IoU 1 and a Chamfer
    below voxel's from 12 dips."""
    bench = load_script("bench_quality")
    rows = bench.main(["--cache", str(tmp_path), "--n", "16", "--meshes", "torus", "--budgets", "12",
                       "--noise", "clean", "--solvers", "truth", "voxel", "--threads", "1"])
    truth, voxel = (next(r for r in rows if r["solver"] == name) for name in ("truth", "voxel"))
    assert truth["iou"] == 1.0 and truth["chamfer"] < voxel["chamfer"] and truth["verdict"] is None
    assert "truth" in capsys.readouterr().out


def test_the_quality_bench_rows_hold_the_consistency_verdict(tmp_path, capsys):
    """Each solved row holds (and prints) the verdict a job records, so a bench case far off in the missing cone
    can be told from one the check flags; a solve stopped after one step does not fit its dips."""
    bench = load_script("bench_quality")
    argv = ["--cache", str(tmp_path), "--n", "16", "--meshes", "torus", "--budgets", "12", "--noise", "clean",
            "--solvers", "voxel", "--threads", "1"]
    converged = bench.main(argv)[0]
    stopped = bench.main([*argv, "--options", 'voxel={"iterations": 1}'])[0]
    assert (converged["verdict"], stopped["verdict"]) == ("consistent", "inconsistent")
    assert converged["chamfer"] < stopped["chamfer"]
    assert capsys.readouterr().out.count(" inconsistent") == 1


@pytest.mark.slow
def test_the_quality_bench_gives_the_same_rows_in_two_worker_processes(tmp_path, capsys, monkeypatch):
    """``--workers 2`` solves the rows in two processes (dearest first) and gives the rows one process
    gives; the two workers share the case cache, whose files are written whole."""
    monkeypatch.syspath_prepend(str(SCRIPTS))  # the workers import the script's functions (run as a script: __main__)
    bench = load_script("bench_quality")
    argv = ["--meshes", "torus", "--generated", "1", "--n", "16", "--dips", "minnorm=12", "voxel=8",
            "--noise", "clean", "--options", 'voxel={"iterations": 60}', "--threads", "1", "--cache", str(tmp_path)]
    two = bench.main([*argv, "--workers", "2"])
    one = bench.main([*argv, "--workers", "1"])

    def table(rows):
        return {(r["mesh"], r["dips"], r["solver"]): r["chamfer"] for r in rows}
    assert sorted(table(two)) == [("gen0", 8, "voxel"), ("torus", 8, "voxel"), ("torus", 12, "minnorm")]
    assert table(two) == pytest.approx(table(one), rel=1e-9)
    assert table(two)[("torus", 8, "voxel")] < 0.05  # a torus, not an empty grid (gen0's limbs are too thin at 16^3)
    assert not list(tmp_path.glob("*.part*"))  # every cache file renamed whole
    assert "RESULT" in capsys.readouterr().out


def test_a_mesh_name_the_quality_bench_does_not_find_is_refused(tmp_path):
    """``--meshes torus torsu`` ran the torus alone, its means and RESULT line over one mesh, exit 0; a name
    not among ``--meshes-dir``'s files is refused before any case, naming it; ``none`` still selects no mesh."""
    bench = load_script("bench_quality")
    argv = ["--cache", str(tmp_path), "--n", "8", "--budgets", "4", "--noise", "clean", "--solvers", "minnorm"]
    with pytest.raises(ValueError, match=r"--meshes: no mesh named torsu in .*meshes \(its meshes: boot, .*torus"):
        bench.run([*argv, "--meshes", "torus", "torsu"])
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="no meshes found"):  # none and no --generated: nothing to run
        bench.run([*argv, "--meshes", "none"])


@pytest.mark.parametrize("argv, message", [
    (["--from-json", "{tmp}/cut.json"], r"--from-json .*cut\.json: not JSON \(Expecting"),
    (["--from-json", "{tmp}/metrics.json"], r"--from-json .*metrics\.json: not the rows of a bench_quality\.py --json "
                                            r"run \(a list of objects holding mesh, .*; it holds a JSON dict\)"),
    (["--options", "voxel={{iterations: 3}}"], r"--options voxel=\{iterations: 3\}: the options must be a JSON object"),
    (["--options", 'voxel={{"iteration": 3}}'], r'--options voxel=\{"iteration": 3\}: the voxel solver takes no '
                                                r"option\(s\) iteration \(did you mean iterations\?\)"),
    (["--options", 'truth={{"iterations": 3}}'], r"--options truth=.*: the truth row solves nothing"),
    (["--workers", "0"], r"--workers must be 1 or more, got 0"),
    (["--budgets", "0"], r"--budgets must be positive numbers of dips, got 0"),
    (["--n", "3"], r"grid resolution n must be an integer >= 4, got 3"),
    (["--meshes", "torsu"], r"--meshes: no mesh named torsu"),
    (["--threads", "-1"], r"--threads must be 1 or more, got -1"),
    (["--threads", "0"], r"--threads must be 1 or more, got 0"),
    (["--seed", "-1"], r"--seed must be 0 or more, got -1"),
    (["--noise", "snr", "--snr", "nan"], r"--snr: snr_db must be a number of dB in \[-20, 200\]"),
    (["--json", "{tmp}/missing/rows.json"], r"--json .*missing/rows\.json: no folder .*missing"),
    (["--generated", "-2"], r"--generated must be 0 or more, got -2"),
    (["--generated", "1", "--generated-first", "-1"], r"--generated-first must be 0 or more"),
    (["--fill", "2"], r"--fill must be in \(0, 1\]"),
    (["--meshes-dir", "{tmp}/nosuch"], r"--meshes-dir .*nosuch: no such folder"),
    (["--meshes-dir", "{tmp}/cut.json"], r"--meshes-dir .*cut\.json: a file, not a folder of mesh files"),
])
def test_bad_options_of_the_quality_bench_are_one_line_and_exit_2(tmp_path, capsys, argv, message):
    """A cut-short or foreign ``--from-json`` file, ``--options`` that are not JSON, ``--n 3``: tracebacks before
    (``JSONDecodeError``, ``AttributeError: 'str' object has no attribute 'get'``, ``ValueError``); ``--workers 0``
    ran with one worker; now one ``error:`` line each, exit 2 (as the script's own checks, which exited 1).
    Before the shared run-option checks: ``--threads -1`` a traceback, ``--threads 0`` and ``--generated -2``
    ignored unsaid, ``--seed -1`` and ``--snr nan`` an error at the first case, ``--json`` in a missing folder one
    after every case, and ``--fill 2`` solved meshes reaching past the grid's slabs, exit 0."""
    (tmp_path / "cut.json").write_text('[{"mesh": "a"')
    (tmp_path / "metrics.json").write_text('{"iou": 0.9}')
    bench = load_script("bench_quality")
    argv = [a.format(tmp=tmp_path) for a in argv]
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--cache", str(tmp_path / "cache"), "--meshes", "torus", "--noise", "clean", "--solvers",
                    "minnorm", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and re.match(f"error: {message}", err), err


def test_a_meshes_dir_without_meshes_says_so(tmp_path):
    """A missing folder, a file, or a folder of no mesh was ``no meshes found in ... (names None)``; the last now says
    what it holds and that --generated is 0 (a missing folder or a file: see the bad-options test)."""
    bench = load_script("bench_quality")
    with pytest.raises(ValueError, match=r"no meshes found: --meshes-dir .* holds no mesh file \(\.ply, \.stl, \.obj, "
                                         r"\.off\) and --generated is 0, so nothing would run"):
        bench.run(["--meshes-dir", str(tmp_path), "--cache", str(tmp_path / "cache")])
    with pytest.raises(ValueError, match=r"no meshes found: nothing to run \(--meshes none and --generated 0"):
        bench.run(["--meshes", "none", "--cache", str(tmp_path / "cache")])
    assert not (tmp_path / "cache").exists()


def test_the_headline_runs_the_solvers_and_budgets_of_dips():
    """``--headline --dips prior=41 minnorm=410`` ran minnorm, voxel and implicit (the default --solvers) and no
    prior, so its RESULT line was nan, exit 0; now --dips sets the plan with --headline too, and the headline's
    ratios take its smallest and largest budgets."""
    bench = load_script("bench_quality")
    args = bench.parse_args(["--headline", "--dips", "prior=41", "minnorm=410"])
    assert args.plan == {"prior": [41], "minnorm": [410]} and args.budgets == [41, 410]
    args = bench.parse_args(["--headline", "--dips", "voxel=20", "minnorm=200"])
    assert args.plan == {"voxel": [20], "minnorm": [200]} and (min(args.budgets), max(args.budgets)) == (20, 200)
    assert bench.parse_args(["--headline"]).plan == {"minnorm": [410], "voxel": [41], "implicit": [41]}


def test_from_json_refuses_a_case_given_twice(tmp_path, capsys):
    """The rows of a torus run at 16^3 and one at 24^3 (rows do not record --n) were averaged as one case: 'meshes 2'
    for one mesh and RESULT minnorm_clean_16_chamfer=0.0161 between the runs' 0.0153 and 0.0170, exit 0; a file
    given twice alike. Now refused naming the case and both files; distinct cases still pool."""
    def rows(chamfer, mesh="torus"):
        return [{"mesh": mesh, "set": "mesh", "dips": k, "noise": "clean", "solver": "minnorm", "seconds": 0.1,
                 "iou": 0.8, "chamfer": chamfer, "hausdorff": 0.1} for k in (8, 16)]
    for name, chamfer, mesh in (("n16", 0.0153, "torus"), ("n24", 0.0170, "torus"), ("bunny", 0.02, "bunny")):
        (tmp_path / f"{name}.json").write_text(json.dumps(rows(chamfer, mesh)))
    bench = load_script("bench_quality")
    for files in (["n16", "n24"], ["n16", "n16"]):
        with pytest.raises(SystemExit) as exit_:
            bench.main(["--from-json", *(str(tmp_path / f"{f}.json") for f in files)])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and re.match(r"error: --from-json: minnorm on torus at 8 dips \(clean\) is in "
                                                  r".*n16\.json and in .*n(16|24)\.json: a file given twice", err), err
    assert len(bench.main(["--from-json", str(tmp_path / "n16.json"), str(tmp_path / "bunny.json")])) == 4


def test_the_quality_bench_unstated_noise_is_the_stated_cases_noise_left_to_the_readings(tmp_path):
    """``--noise unstated``: the scan of ``--noise snr`` preprocessed without its noise statement, so its
    measurement holds no sigma and the solvers take the readings' (``readings_slab_sigma``) instead."""
    bench = load_script("bench_quality")
    args = bench.parse_args(["--cache", str(tmp_path), "--n", "16", "--noise", "unstated"])
    grid = bench.Grid(16)
    stated, _, _ = bench.case_data(args, MESHES_DIR / "torus.ply", grid, 6, "snr")
    unstated, _, _ = bench.case_data(args, MESHES_DIR / "torus.ply", grid, 6, "unstated")
    assert stated.sigma is not None and stated.metadata["readings_slab_sigma"] is None
    assert unstated.sigma is None
    assert unstated.metadata["readings_slab_sigma"] == pytest.approx(float(stated.sigma.median()), rel=0.3)
    np.testing.assert_allclose(unstated.profiles.numpy(), stated.profiles.numpy(), rtol=0,
                               atol=1e-3 * float(stated.profiles.max()))
    assert len(list(tmp_path.glob("*_unstated30.0_*.npz"))) == 1


def test_the_quality_bench_max_tilt_dips_along_a_limited_reach_and_keeps_the_hemisphere_cache(tmp_path):
    """``--max-tilt-deg 35``: the dips of a rig that tilts 0-35 deg (the plan the tilt-35 weights were trained on),
    cached apart from the hemisphere's; outside (0, 90] refused."""
    bench = load_script("bench_quality")
    grid = bench.Grid(16)
    hemisphere = bench.parse_args(["--cache", str(tmp_path), "--n", "16"])
    limited = bench.parse_args(["--cache", str(tmp_path), "--n", "16", "--max-tilt-deg", "35"])
    full, _, _ = bench.case_data(hemisphere, MESHES_DIR / "torus.ply", grid, 12, "clean")
    tilted, _, _ = bench.case_data(limited, MESHES_DIR / "torus.ply", grid, 12, "clean")
    tilts = np.degrees(np.arccos(np.clip(tilted.directions[:, 2].abs().numpy(), 0, 1)))
    assert tilts.max() <= 35 + 1e-6 and tilts.max() > 20
    assert np.degrees(np.arccos(np.clip(full.directions[:, 2].abs().numpy(), 0, 1))).max() > 60
    assert len(list(tmp_path.glob("*_t35_*.npz"))) == 1 and len(list(tmp_path.glob("*.npz"))) == 2
    for bad in ("0", "91"):
        with pytest.raises(ValueError, match="--max-tilt-deg must be in"):
            bench.parse_args(["--max-tilt-deg", bad])


def test_the_quality_cache_is_keyed_by_the_mesh_files_bytes(tmp_path):
    """Two ``--meshes-dir`` holding a file of the same name (or one file edited): the second run was handed the
    first's simulated dips and truth (a bunny scored as the torus: IoU 0.667 and Chamfer 0.1099 for its own 0.583
    and 0.0366 at 16^3, 12 dips, exit 0); now each file's bytes key its cases."""
    bench = load_script("bench_quality")
    for folder, mesh in (("a", "torus"), ("b", "bunny")):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "obj.ply").write_bytes((MESHES_DIR / f"{mesh}.ply").read_bytes())
    args = bench.parse_args(["--cache", str(tmp_path / "cache"), "--n", "8"])
    grid = bench.Grid(8)
    torus, torus_truth, _ = bench.case_data(args, tmp_path / "a" / "obj.ply", grid, 3, "clean")
    bunny, bunny_truth, shape = bench.case_data(args, tmp_path / "b" / "obj.ply", grid, 3, "clean")
    assert len(list((tmp_path / "cache").iterdir())) == 4
    assert float(bunny.profiles.sum()) != pytest.approx(float(torus.profiles.sum()), rel=1e-3)
    assert (bunny_truth == (shape.occupancy(grid, supersample=bench.TRUTH_SUPERSAMPLE).numpy() >= 0.5)).all()


@pytest.mark.parametrize("script", ["bench_scale", "bench_planning"])
def test_a_mesh_name_not_bundled_is_refused_before_any_case(script, capsys):
    """``--meshes torus nosuch``: a traceback when the loop reached it, after the meshes before it; now refused by
    the argument parser, exit 2, naming it."""
    with pytest.raises(SystemExit) as exit_:
        load_script(script).parse_args(["--meshes", "torus", "nosuch"])
    assert exit_.value.code == 2
    assert "error: --meshes: no bundled mesh 'nosuch'; bundled: boot, " in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--fill", "2"], r"--fill must be in \(0, 1\] \(the mesh's radius over the working ball's: above 1 the mesh "
                      r"reaches beyond the working ball, which the grid cannot hold\), got 2"),
    (["--fill", "0"], r"--fill must be in \(0, 1\]"),
    (["--budget", "5"], r"--n 32, --budget 5, --batch 8, --initial 8, --cap-tilt 35, --large 123: need 1 <= "
                        r"initial_dips <= budget"),
    (["--batch", "0"], r".*need 1 <= initial_dips <= budget and batch_size >= 1"),
    (["--cap-tilt", "100"], r".*tilt range must satisfy 0 <= min <= max <= 90 degrees"),
    (["--large", "0"], r".*number of orientations must be a positive integer, got 0"),
    # were a traceback (RuntimeError: set_num_threads expects a positive integer) from a worker process, rc 1; a
    # traceback naming snr_db, not --snr; --jobs 0 run as the default (2 with --quick), unsaid
    (["--threads", "0"], r"argument --threads: must be 1 or more \(torch threads\), got 0"),
    (["--snr", "nan"], r"--snr: snr_db must be a number of dB in \[-20, 200\]"),
    (["--jobs", "0"], r"--jobs must be 1 or more \(meshes benchmarked at once\), got 0"),
    # were a late error (--oracle -1: "negative dimensions are not allowed", naming no option)
    (["--oracle", "-1"], r"argument --oracle: must be 0 or more \(random rotations\), got -1"),
    (["--oracle-pool", "-1"], r"argument --oracle-pool: must be 0 or more \(candidates per dip\), got -1"),
])
def test_bad_options_of_the_planning_bench_are_refused_before_any_mesh(capsys, argv, message):
    """The audit's case: ``--fill 2`` (a torus twice the working ball, 16^3) ran every plan and printed
    ``RESULT adaptive41_over_fib123=1.009 adaptive41_over_fib41=1.003 cap_adaptive_over_uniform=0.990``, exit 0, for a
    mesh the grid cannot hold; ``--budget 5``, ``--batch 0``, ``--cap-tilt 100`` and ``--large 0`` gave tracebacks
    after the plans before them. Now one ``error:`` line each, exit 2, before any mesh."""
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_planning").parse_args(["--quick", "--meshes", "torus", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and re.search(f"error: {message}", err), err


def test_the_reference_plans_table_and_result_line(capsys):
    """Coverage per (plan, ball) over its determined pairs; the worst parameter among those determined on at least
    5 rigs (a parameter determined on fewer does not count), from hand-made rows."""
    bench = load_script("bench_reference_plans")
    args = bench.parse_args(["--rigs", "6"])
    found = {("grid16", "ball"): {"pivot_mm": [(True, 0.1)] * 5 + [(False, 2.5)], "tilt_zero_deg": [(False, 3.0)]},
             ("grid16", "offball"): {"pivot_mm": [(True, -0.2)] * 6},
             ("fibonacci41", "ball"): {"step_scale": [(True, 0.0)] * 4 + [(False, 1.9)] * 2},
             ("fibonacci41", "offball"): {}}
    bench.print_table(found, args)
    out = capsys.readouterr().out
    assert "| grid16 | ball | pivot_mm | 6/6 | 5/6 | +0.50 | 0.89 |" in out
    assert "| grid16 | ball | tilt_zero_deg | 1/6 | 0/1 |" in out
    assert out.strip().splitlines()[-1] == (
        "RESULT grid16_ball_coverage90=0.714 grid16_offball_coverage90=1.000 fibonacci41_ball_coverage90=0.667 "
        "fibonacci41_offball_coverage90=nan worst_parameter_coverage90=0.667 "
        "worst_parameter=fibonacci41:ball:step_scale")
    bench.print_table({("grid16", "ball"): {"pivot_mm": [(True, 0.1)] * 6}}, args)
    assert capsys.readouterr().out.strip().endswith("worst_parameter_coverage90=1.000 worst_parameter=none")


def test_the_reference_plans_standard_errors_are_of_determined_parameters():
    bench = load_script("bench_reference_plans")
    report = CalibrationReport(estimates={"pivot_mm": 2.0, "spin_zero_deg": 0.0}, standard_errors={"pivot_mm": 0.5,
                               "spin_zero_deg": 1.0}, correlations={}, undetermined={"spin_zero_deg": "symmetric"},
                               intervals={"pivot_mm": (1.0, 3.0)})
    assert bench.standard_errors(report, {"pivot_mm": 1.5, "spin_zero_deg": 2.0}) == {"pivot_mm": 1.0}


def test_the_reference_plans_grid_plans_tilt_as_named():
    """``grid16`` reaches 70 deg, ``grid16_35`` (a rig like the authors') 35 deg, both at four spins per tilt."""
    bench = load_script("bench_reference_plans")
    for name, top in (("grid16", 70.0), ("grid16_35", 35.0)):
        tilt = np.degrees(np.arccos(bench.PLANS[name][:, 2]))
        assert bench.PLANS[name].shape == (16, 3) and np.isclose(tilt.max(), top) and tilt.min() < 1e-3
    assert bench.parse_args([]).plans == ["grid16", "fibonacci41"]


def _symmetry_row(cls, misfit, p_value, rejected, shape="disk_2d", declared="mirror_x"):
    return {"shape": shape, "declared": declared, "class": cls, "reference_misfit": 0.0, "dips": 12, "snr_db": None,
            "misfit": misfit, "p_value": p_value, "rejected": rejected}


def test_the_symmetry_check_table_and_result_line(capsys):
    """Per class the share rejected, the largest significant misfit and the smallest rejected one, from hand-made
    rows; the declarations an asymmetric class kept and a symmetric one lost are named."""
    bench = load_script("bench_symmetry_check")
    rows = [_symmetry_row("symmetric", 0.0012, 0.5, False), _symmetry_row("symmetric", 0.0008, 1e-5, False),
            _symmetry_row("asymmetric", 0.2, 1e-9, True, "elephant_2d"),
            _symmetry_row("asymmetric", 0.03, 0.01, False, "fish", "rotation2_z"),
            _symmetry_row("near", 0.02, 1e-4, True, "penguin")]
    bench.print_table(rows, bench.parse_args(["--trials", "1"]))
    out = capsys.readouterr().out
    assert "| symmetric | 1 | 2 | 0 | 0.000 | 0.0010 | 0.0008 | nan |" in out
    assert "| asymmetric | 2 | 2 | 1 | 0.500 | 0.1150 | 0.2000 | 0.2000 |" in out
    assert "declarations kept: fish:rotation2_z (12 dips)" in out and "symmetric declarations rejected: none" in out
    assert "near declarations (noise-free misfit, rejected / trials): penguin:mirror_x 0.0000 1/1" in out
    assert out.strip().splitlines()[-1] == (
        "RESULT false_rejections=0.000 detected_asymmetric=0.500 detected_near=1.000 trials=5")


def test_the_symmetry_check_declares_each_shape_its_own_groups_and_classes_by_misfit():
    bench = load_script("bench_symmetry_check")
    ball, disk = bench.declarations("ball_3d", 3), bench.declarations("disk_2d", 2)
    assert len(ball["dihedral4_z"]) == 8 and len(ball["rotation4_z"]) == 4 and len(disk["rotation3"]) == 3
    assert [bench.classify(m) for m in (0.001, 0.01, 0.06)] == ["symmetric", "near", "asymmetric"]


def _main_in_this_process(bench, argv: list[str]):
    """``bench.main(argv)``, then dipnet's log level and torch's threads restored: the scripts quiet dipnet's log and
    set torch's threads for their whole process, not for the tests run after them in this one."""
    log, level, threads = logging.getLogger("dipnet"), logging.getLogger("dipnet").level, torch.get_num_threads()
    try:
        return bench.main(argv)
    finally:
        log.setLevel(level)
        torch.set_num_threads(threads)


def test_the_symmetry_check_runs_end_to_end_on_chosen_shapes(capsys):
    """The 2D disk and elephant, one random scan each: the disk keeps its mirrors and rotations, the elephant loses
    its mirrors; an unknown shape is named."""
    bench = load_script("bench_symmetry_check")
    rows = _main_in_this_process(bench, ["--trials", "1", "--shapes", "disk_2d", "elephant_2d", "--threads", "1"])
    assert {r["shape"] for r in rows} == {"disk_2d", "elephant_2d"} and len(rows) == 8
    assert not any(r["rejected"] for r in rows if r["shape"] == "disk_2d")
    assert all(r["rejected"] for r in rows if r["shape"] == "elephant_2d" and r["declared"].startswith("mirror"))
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("RESULT false_rejections=0.000 ")
    with pytest.raises(ValueError, match="no shape named teapot"):
        bench.shapes(["teapot"])


def test_the_dip_agreement_bench_scores_correct_scans_and_their_faults(capsys):
    """One random scan of the chamber box and the box (24 slabs) and their four faults; the correct ones and the
    authors' real recording have no outlier, and the RESULT line holds the rates; a 2D or unknown shape is refused."""
    bench = load_script("bench_dip_agreement")
    rows = _main_in_this_process(bench, ["--trials", "1", "--shapes", "chamber_box_3d", "box_3d", "--threads", "1",
                                         "--resolution", "24", "--seed", "5"])
    assert [r["kind"] for r in rows] == list(bench.KINDS) * 2
    assert all(r["tested"] > 0 and len(r["flags"]) == len(bench.LIMITS) for r in rows)
    assert not any(r["flags"][0] for r in rows if r["kind"] == "ok")
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("RESULT false_alarms=0.000 detected_swap=") and last.endswith(" cats_outliers=0 cases=2")
    for shapes in (["elephant_2d"], ["teapot"]):  # refused before the run sets its threads and quiets the log
        with pytest.raises(SystemExit) as exit_:
            _main_in_this_process(bench, ["--shapes", *shapes])
        assert exit_.value.code == 2 and "error: --shapes: no shape named" in capsys.readouterr().err


def _consistency_row(kind, iou, residual, expected, snr_db=None, shape="ball_3d", seed=1):
    limit = max(3 * expected, 0.05)
    return {"shape": shape, "ndim": 3, "n": 48, "dips": 30, "snr_db": snr_db, "noise_seed": seed, "shift_axis": 0,
            "shift_sign": 1, "other": "box_3d", "kind": kind, "iou": iou, "residual": residual, "expected": expected,
            "ratio": residual / expected, "limit": limit, "noise_source": "sigma" if snr_db else "estimated",
            "verdict": "inconsistent" if residual > limit else "consistent", "residual_flagged": residual > limit}


def test_the_consistency_bench_counts_false_alarms_and_detections_per_rule(capsys):
    """From hand-made rows (48 voxels per axis: the floor 0.05): a correct result at 10 dB with residual 1.8 x
    expected is a false alarm of f1.5, f1.25, hypot1.5 and hypot1.25 only; a wrong ball at 2.5 x expected is detected
    by f2, hypot2 and below, not by the row's own limit (current, here 3 x expected) or the rule before; the truth and
    a reconstruction between the IoU classes count in neither."""
    bench = load_script("bench_consistency")
    rows = [_consistency_row("reconstruction", 0.9, 0.18, 0.1, 10.0), _consistency_row("ball", 0.6, 0.25, 0.1, 10.0),
            _consistency_row("truth", 1.0, 0.3, 0.1, 10.0), _consistency_row("reconstruction", 0.82, 0.5, 0.1, 20.0,
                                                                           seed=2)]
    bench.print_table(rows, bench.parse_args(["--trials", "1"]))
    out = capsys.readouterr().out
    assert "| 5-15 dB | 1 | 1 | 0 | 0 | 1.80 | 1.80 | 1.80 | 0.000 | 0.000 | 1 | 2.50 | 2.50 | 2.50 |" in out
    assert "| 15-30 dB | 1 | 0 | 1 | 0 |" in out
    result = dict(item.split("=") for item in out.strip().splitlines()[-1].split()[1:])
    assert (result["false_alarms_current"], result["detected_current"]) == ("0.000", "0.000")
    assert (result["false_alarms_f2"], result["detected_f2"]) == ("0.000", "1.000")
    assert (result["false_alarms_f1.5"], result["detected_f1.5"]) == ("1.000", "1.000")
    assert (result["false_alarms_before"], result["detected_before"]) == ("0.000", "0.000")
    assert (result["false_alarms_hypot1.5"], result["detected_hypot1.5"]) == ("1.000", "1.000")
    assert result["cases"] == "2" and "f3" not in {key.rpartition("_")[2] for key in result}
    assert "rules without a false alarm: current, before, f2, hypot2, hypot3; the most detections among them: f2" in out
    assert "wrong candidates the current rule passes (1): ball_3d:ball (5-15 dB, IoU 0.60" in out


def test_the_consistency_bench_candidates_keep_the_volume_and_move_as_asked():
    """The ball and the other shape hold as many voxels as asked, about the centre asked; a shift moves the voxels by
    two along the array axis and loses what leaves the grid."""
    bench = load_script("bench_consistency")
    grid = bench.Grid(16, 3, 100.0)
    centre = np.array([12.5, 0.0, -6.25])
    ball = bench.ball_candidate(grid, 200, centre)
    assert ball.sum() == 200 and np.allclose(grid.centers().numpy()[ball].mean(0), centre, atol=grid.voxel_size / 2)
    other = bench.other_shape_candidate(bench.shape_makers()["torus_3d"][1], grid, 300, centre)
    assert other.sum() == 300 and np.allclose(grid.centers().numpy()[other].mean(0), centre, atol=grid.voxel_size)
    line = np.zeros((6, 4), dtype=bool)
    line[0, 1] = line[5, 2] = True
    moved = bench.shifted(line, 0, 2)
    assert moved[2, 1] and moved.sum() == 1 and bench.shifted(line, 0, -2)[3, 2]
    assert [bench.band(s) for s in (None, 40.0, 30.0, 15.0, 5.0)] == ["noise-free", "30-40 dB", "30-40 dB",
                                                                      "15-30 dB", "5-15 dB"]


def test_the_consistency_bench_runs_end_to_end_on_chosen_shapes(capsys):
    """The 2D disk and the 3D ball, one random scan each: every case checks its reconstruction, its truth and three
    wrong candidates; the RESULT line holds every rule's rates, in [0, 1] (or NaN when no case of the class came
    up); an unknown shape is named."""
    bench = load_script("bench_consistency")
    rows = _main_in_this_process(bench, ["--trials", "1", "--shapes", "disk_2d", "ball_3d", "--threads", "1"])
    assert {r["shape"] for r in rows} == {"disk_2d", "ball_3d"} and len(rows) == 10
    assert {r["kind"] for r in rows} == {"reconstruction", "truth", "ball", "shifted", "other"}
    recons = [r for r in rows if r["kind"] == "reconstruction"]
    assert all(np.isfinite(r["ratio"]) and r["ratio"] > 0 and r["iou"] > 0.5 for r in recons)
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("RESULT false_alarms_current=")
    result = dict(item.split("=") for item in last.split()[1:])
    rates = [key for key in result if key != "cases"]
    assert len(rates) == 2 * len(bench.rules()) and {"false_alarms_f1.5", "detected_f1.5"} <= set(rates)
    assert all(0.0 <= float(result[key]) <= 1.0 or np.isnan(float(result[key])) for key in rates)
    assert result["cases"] == "2"
    with pytest.raises(ValueError, match="no shape named teapot"):
        bench.shape_names(["teapot"])


@pytest.mark.slow
def test_the_pockets_bench_runs_end_to_end_and_finds_the_chamber_boxs_flooding(capsys):
    """The chamber box (its chamber opens through one channel) and the ball, one scan each of 10 dips: the chamber
    box traps air or keeps a vessel in most dips, preprocessing finds the level falling in vessel dips and nowhere
    else, and the ball traps nothing; a 2D shape is refused by name."""
    bench = load_script("bench_pockets")
    rows = _main_in_this_process(bench, ["--shapes", "chamber_box_3d", "ball_3d", "--dips", "10", "10",
                                         "--resolution", "16", "--threads", "1"])
    box, ball = sorted(rows, key=lambda r: r["shape"] != "chamber_box_3d")
    assert max(box["pocket_share"]) + max(box["vessel_share"]) > 0.1
    assert max(ball["pocket_share"]) == max(ball["vessel_share"]) == 0.0 and ball["iou_plain"] == ball["iou_pockets"]
    vessels, found, clean, false_falls = bench.dip_counts(box)
    assert found >= 1 and false_falls == 0 and bench.dip_counts(ball) == (0, 0, 10, 0)
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("RESULT affected=") and last.endswith("cases=2")
    with pytest.raises(ValueError, match="no shape named disk_2d"):
        bench.shape_names(["disk_2d"], ndim=3)


@pytest.mark.parametrize("script", ["bench_scale", "bench_reference_plans", "bench_calibration", "bench_symmetry_check",
                                    "bench_consistency", "bench_pockets", "bench_dip_agreement", "bench_planning"])
@pytest.mark.parametrize("threads", ["0", "-2", "two"])
def test_threads_below_one_are_refused_by_every_benchmark(script, threads, capsys):
    """``--threads 0`` was torch's ``RuntimeError: set_num_threads expects a positive integer`` traceback, exit 1,
    in six benchmarks (the pool benchmarks and bench_scale, bench_reference_plans, bench_calibration,
    bench_symmetry_check); now argparse's one line naming --threads, exit 2."""
    with pytest.raises(SystemExit) as exit_:
        load_script(script).parse_args(["--threads", threads])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "error: argument --threads: must be " in err, err


@pytest.mark.parametrize("script, argv, message", [
    # bench_calibration: --rigs 0 was "StatisticsError: no median for empty data" after the run, rc 1; the others ran
    # (--fill 2: a mesh past the working ball) or failed at the first rig (--snr nan, --seed -1, --dips 0), and --json
    # in a missing folder after the first rig's minutes
    ("bench_calibration", ["--quick", "--rigs", "0"], r"argument --rigs: must be 1 or more \(random rigs\), got 0"),
    ("bench_calibration", ["--seed", "-1"], r"--seed must be 0 or more, got -1"),
    ("bench_calibration", ["--snr", "nan"], r"--snr: snr_db must be a number of dB in \[-20, 200\]"),
    ("bench_calibration", ["--fill", "2"], r"--fill must be in \(0, 1\]"),
    ("bench_calibration", ["--dips", "0"], r"argument --dips: must be 1 or more \(dips\), got 0"),
    ("bench_calibration", ["--iterations", "0"], r"argument --iterations: must be 1 or more"),
    ("bench_calibration", ["--json", "/nonexistent/dir/rigs.json"], r"--json /nonexistent/dir/rigs.json: no folder"),
    ("bench_calibration", ["--n", "3"], r"argument --n: grid resolution n must be an integer >= 4, got 3"),
    ("bench_calibration", ["--ball-offset", "nan"], r"argument --ball-offset: must be a finite number of mm off"),
    # bench_reference_plans: --snr nan was a ValueError traceback naming snr_db, rc 1
    ("bench_reference_plans", ["--quick", "--rigs", "1", "--snr", "nan"], r"--snr: snr_db must be a number of dB"),
    ("bench_reference_plans", ["--rigs", "0"], r"argument --rigs: must be 1 or more"),
    ("bench_reference_plans", ["--seed", "-1"], r"--seed must be 0 or more, got -1"),
    ("bench_reference_plans", ["--ball-offset", "-5"], r"argument --ball-offset: must be a finite number of mm off the "
                                                       r"spin axis, 0 or more, got '-5'"),
    # bench_symmetry_check --trials 0 ran 23 shapes of no trial, exit 0
    ("bench_symmetry_check", ["--quick", "--trials", "0"], r"argument --trials: must be 1 or more \(random scans per"),
    ("bench_symmetry_check", ["--seed", "-3"], r"--seed must be 0 or more, got -3"),
    # the pool benchmarks (--trials, --seed, --resolution, --json of add_pool_options)
    ("bench_dip_agreement", ["--trials", "0"], r"argument --trials: must be 1 or more"),
    ("bench_dip_agreement", ["--resolution", "-1"],
     r"argument --resolution: grid resolution n must be an integer >= 4, got -1 \(or 0: drawn per case\)"),
    ("bench_dip_agreement", ["--json", "/nonexistent/dir/rows.json"], r"--json /nonexistent/dir/rows.json: no folder"),
    ("bench_consistency", ["--resolution", "0"],
     r"argument --resolution: grid resolution n must be an integer >= 4, got 0"),
    ("bench_consistency", ["--seed", "-1"], r"--seed must be 0 or more, got -1"),
    ("bench_pockets", ["--dips", "30", "20"], r"--dips LOW HIGH: LOW must not be above HIGH, got 30 20"),
    ("bench_pockets", ["--dips", "0", "5"], r"argument --dips: must be 1 or more \(dips\), got 0"),
    ("bench_pockets", ["--resolution", "2"],
     r"argument --resolution: grid resolution n must be an integer >= 4, got 2"),
    # bench_scale checked --meshes and --threads only
    # bench_quality --quantum-mm -1 / nan were an error naming quantum_mm, not the flag, at the first simulated case
    ("bench_quality", ["--quantum-mm", "-1"], r"argument --quantum-mm: must be a finite number of mm, 0 or more"),
    ("bench_quality", ["--quantum-mm", "nan"], r"argument --quantum-mm: must be a finite number of mm, 0 or more"),
    ("bench_scale", ["--n", "3"], r"argument --n: grid resolution n must be an integer >= 4, got 3"),
    ("bench_scale", ["--fractions", "0"], r"argument --fractions: must be a finite number of dips per N\^2"),
    ("bench_scale", ["--snr", "nan"], r"--snr: snr_db must be a number of dB"),
    ("bench_scale", ["--fill", "0"], r"--fill must be in \(0, 1\]"),
    ("bench_scale", ["--eps", "-1"], r"argument --eps: must be a finite number of NUFFT tolerance above 0"),
    ("bench_scale", ["--upsampfac", "1"],
     r"argument --upsampfac: must be a finite number of NUFFT oversampling above 1"),
    ("bench_scale", ["--voxel-iters", "0"], r"argument --voxel-iters: must be 1 or more"),
    ("bench_scale", ["--json", "/nonexistent/dir/rows.json"], r"--json /nonexistent/dir/rows.json: no folder"),
    # bench_monitor and bench_operator checked none (--repeats 0: no scan, then a traceback; --limit nan
    # skipped no case, however long)
    ("bench_monitor", ["--dips", "0"], r"argument --dips: must be 1 or more \(dips\), got 0"),
    ("bench_monitor", ["--step", "nan"], r"argument --step: must be a finite number of mm above 0, got 'nan'"),
    ("bench_monitor", ["--settle", "-1"], r"argument --settle: must be a finite number of seconds, 0 or more"),
    ("bench_monitor", ["--repeats", "0"], r"argument --repeats: must be 1 or more \(runs each way\), got 0"),
    ("bench_monitor", ["--resolution", "2"],
     r"argument --resolution: grid resolution n must be an integer >= 4, got 2"),
    ("bench_operator", ["--sizes", "64", "3"], r"argument --sizes: grid resolution n must be an integer >= 4, got 3"),
    ("bench_operator", ["--orientations", "0"], r"argument --orientations: must be 1 or more \(dips\), got 0"),
    ("bench_operator", ["--limit", "nan"], r"argument --limit: must be a finite number of seconds above 0 \(inf: no "
                                           r"limit\), got 'nan'"),
    ("bench_operator", ["--memory-limit", "0"], r"argument --memory-limit: must be a finite number of GB above 0"),
    ("bench_operator", ["--radon-size", "-5"],
     r"argument --radon-size: grid resolution n must be an integer >= 4, got -5 \(or 0: skip\)"),
    ("bench_operator", ["--lsqr-iterations", "0"], r"argument --lsqr-iterations: must be 1 or more"),
])
def test_bad_options_of_every_benchmark_are_refused_before_any_case(script, argv, message, capsys):
    """Each benchmark refuses its own flags in ``parse_args`` (the shared types and checks of
    ``dipnet.experiments.bench_options``): argparse's one line naming the flag, exit 2, before any case."""
    with pytest.raises(SystemExit) as exit_:
        load_script(script).parse_args(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and re.search(f"error: {message}", err), err


def test_the_operator_benchmark_takes_no_limit_and_no_radon_comparison():
    args = load_script("bench_operator").parse_args(["--limit", "inf", "--memory-limit", "inf", "--radon-size", "0"])
    assert (args.limit, args.memory_limit, args.radon_size) == (float("inf"), float("inf"), 0)


def test_a_bad_shape_name_is_one_line_and_exit_2(capsys):
    """The benchmarks' ``main`` runs under ``user_errors``: a ``ValueError`` before the cases (here ``--shapes`` naming
    no shape) was a traceback, exit 1; now one ``error:`` line, exit 2."""
    with pytest.raises(SystemExit) as exit_:
        load_script("bench_dip_agreement").main(["--shapes", "nosuch", "--threads", "1"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith("error: --shapes: no shape named nosuch") and err.count("\n") == 1
