"""Multirun smoke tests of scripts/reconstruct.py: tiny 2D sweeps with the basic sweeper and with
the joblib launcher (skipped when hydra-joblib-launcher is missing), a failing job that does not
stop the sweep, and the experiment presets composing."""

from __future__ import annotations

import importlib.util
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dipnet.experiments import collect

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "reconstruct.py"
TINY = ["ndim=2", "resolution=24", "output.figures=false", "output.progress=false"]


def reconstruct(*args: str, cwd: Path, returncode: int = 0) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=240)
    assert proc.returncode == returncode, proc.stderr[-3000:]
    return proc


def check_sweep(sweep: Path, n_dips: list[int]) -> list[collect.Run]:
    runs = collect.collect_runs(sweep)
    assert [r.status for r in runs] == ["ok"] * len(n_dips), [r.error for r in runs]
    check_runs(runs, n_dips)
    return runs


def check_runs(runs: list[collect.Run], n_dips: list[int]) -> None:
    """Each finished run has its ``n_dips``, a fair IoU and its reconstruction and measurement files."""
    for run, n in zip(runs, n_dips, strict=True):
        assert run.config["n_dips"] == n and f"n_dips={n}" in run.overrides
        assert run.metrics["n_dips"] == n and 0.5 < run.metrics["iou"] <= 1.0
        assert (run.path / "reconstruction.npz").is_file() and (run.path / "measurement.npz").is_file()


def test_basic_sweeper_runs_every_job_and_a_failing_one_does_not_stop_the_sweep(tmp_path):
    """One sweep (one subprocess, ~6 s of importing torch) of a failing job then two good ones: the
    basic sweeper runs each, the job log says which finished, and the failure stops nothing; the sweep then exits 1
    (the failed job named)."""
    sweep = tmp_path / "sweep"
    proc = reconstruct("-m", *TINY, "n_dips=0,6,12", "hydra/callbacks=job_log", f"hydra.sweep.dir={sweep}",
                       cwd=tmp_path, returncode=1)
    runs = collect.collect_runs(sweep)
    log = proc.stdout + proc.stderr
    assert [r.status for r in runs] == ["failed", "ok", "ok"], [r.error for r in runs]
    assert "n_dips" in runs[0].error and (runs[0].path / "error.txt").is_file()
    check_runs(runs[1:], [6, 12])  # the jobs after the failed one ran to the end
    assert "job 0 failed" in log and "job 1 done" in log and "job 2 done" in log, log[-3000:]
    assert "sweep finished: 2 of 3 jobs ok" in log, log[-3000:]
    assert proc.stderr.rstrip().endswith(f"error: 1 of 3 jobs of the sweep in {sweep} failed or did not finish "
                                         "(listed above, each with its error.txt): the sweep exits 1")


@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_joblib_launcher") is None,
                    reason="needs hydra-joblib-launcher (pip install -e '.[sweeps]')")
@pytest.mark.slow
def test_joblib_launcher_two_jobs(tmp_path):
    sweep = tmp_path / "sweep"
    reconstruct("-m", *TINY, "n_dips=6,12", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
                f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    check_sweep(sweep, [6, 12])


@pytest.mark.parametrize("preset", ["paper_2d", "dips_sweep", "snr_sweep", "table1"])
def test_experiment_presets_compose(preset, tmp_path):
    from hydra import compose, initialize_config_module

    with initialize_config_module(version_base="1.3", config_module="dipnet.conf"):
        extra = ["meshes_dir=/meshes"] if preset == "table1" else []
        cfg = compose("config", overrides=[f"experiment={preset}", *extra], return_hydra_config=True)
    params = cfg.hydra.sweeper.params or {}
    if preset == "paper_2d":
        assert (cfg.ndim, cfg.n_dips, cfg.shape.name) == (2, 20, "elephant")
        assert cfg.solver._target_.endswith("LSMRSolver")
    elif preset == "table1":
        assert cfg.shape.path == "/meshes/bunny.ply" and "mesh" in params
    else:
        assert str(cfg.hydra.sweep.dir) == f"sweeps/{preset}" and len(params) == 2


@pytest.mark.slow
def test_the_hint_of_a_cut_sweep_resumes_the_cut_job_alone(tmp_path):
    """Ctrl-C in job 1 of 3 (checkpointed voxel solves): the hint's single run resumes job 1 from its checkpoint into
    its folder and runs nothing else (before, the hint's "rerun the same command with hydra.run.dir=SWEEP/1" reran the
    sweep, every job of it)."""
    sweep = tmp_path / "sweep"
    args = ["-m", f"hydra.sweep.dir={sweep}", "resolution=16", "n_dips=12", "solver=voxel", "solver.tol=0",
            "output.checkpoint=true", "output.figures=false", "output.uncertainty=false",
            "output.resolvability=false", "output.progress=false", "threads=1", "solver.iterations=20,3000,20"]
    proc = subprocess.Popen([sys.executable, str(SCRIPT), *args], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120  # job 1's solve (3000 steps a stage) has saved its first checkpoint
    while not list((sweep / "1" / "checkpoints").glob("*.pt")) and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    hint = next(line for line in stderr.splitlines() if line.startswith("interrupted: "))
    assert proc.returncode == 130 and "Job 2 of the sweep's 3 did not start" in hint, stderr[-2000:]
    single = hint.split("run it once into its folder: ")[1].split(". Job 2")[0]
    words = shlex.split(single)
    assert words[:2] == ["python", "scripts/reconstruct.py"] and words[-1] == f"hydra.run.dir={sweep / '1'}"
    resumed = reconstruct(*words[2:], cwd=tmp_path)
    assert "resumed 'voxel" in resumed.stdout + resumed.stderr
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "1", "multirun.yaml"]  # job 2 did not run
    runs = collect.collect_runs(sweep)
    assert [r.status for r in runs] == ["ok", "ok"] and runs[1].metrics["n_dips"] == 12
    assert runs[1].config["solver"]["iterations"] == 3000
