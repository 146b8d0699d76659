"""Issue 22, files and lost work: two jobs never share a run directory, damaged checkpoints never
block a rerun, a full disk never buries the safe-stop message. Each case runs the command as a
user would: a subprocess of the script, or its Hydra entry point in this process with the same arguments
(tests/script_runs.py) where only its output and exit code are checked."""

from __future__ import annotations

import copy
import functools
import json
import os
import pickle
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from dipnet.core.locks import CHECKPOINT_LOCK_NAME, HeldLock
from dipnet.experiments.collect import collect_runs
from script_modules import load_script
from script_runs import one_line_error, run_script

ROOT = Path(__file__).resolve().parents[2]
RECONSTRUCT = ROOT / "scripts" / "reconstruct.py"
SCAN = ROOT / "scripts" / "scan.py"
QUICK = ["output.progress=false", "output.figures=false", "output.uncertainty=false",
         "output.resolvability=false", "resolution=16", "n_dips=12", "shape.name=ball"]
QUICK_SCAN = ["n_dips=2", "protocol.step_mm=20", "fsync=false", "progress=false"]


def _script(script: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(script), *overrides], capture_output=True, text=True, timeout=300)


@contextmanager
def _job_in(directory: Path) -> Iterator[int]:
    """Another process holding ``directory`` as a running job does; yields its pid."""
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from dipnet.core.locks import run_directory_lock\n"
                               f"with run_directory_lock({str(directory)!r}):\n"
                               "    print('held', flush=True); sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        yield holder.pid
    finally:
        holder.communicate("", timeout=60)


# ----------------------------------------------------------------------------- portability
@pytest.mark.slow
def test_dipnet_imports_without_fcntl():
    """Before: ``import dipnet`` failed on Windows (``fcntl`` imported by the scan-file lock)."""
    code = ("import sys, serial\n"  # pyserial brings its own backend per platform (serialwin32 on Windows)
            "sys.modules['fcntl'] = None\n"  # then, as on Windows, import fcntl fails
            "import dipnet, dipnet.core.locks, dipnet.rig.runner, dipnet.jobs.pipeline; print('imported')")
    proc = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "imported", proc.stderr[-2000:]


# ----------------------------------------------------------------------------- run directory lock
@pytest.mark.parametrize("script,overrides", [(RECONSTRUCT, QUICK), (SCAN, QUICK_SCAN)])
@pytest.mark.slow
def test_second_job_into_a_busy_run_directory_is_refused(tmp_path, script, overrides):
    """Before: both jobs exited 0 saying "outputs written"; only the second one's files remained."""
    with _job_in(tmp_path) as pid:
        line = one_line_error(_script(script, f"hydra.run.dir={tmp_path}", *overrides))
    assert re.match(rf"error: run directory {re.escape(str(tmp_path))} is in use by another job \(pid {pid} on "
                    r".+, since \d{4}-\d\d-\d\dT[\d:]+[+-]\d{4}\): wait for it to finish, stop it, or choose another "
                    r"output directory \(hydra\.run\.dir=\.\.\.\)$", line), line
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "rawscan.jsonl").exists()
    done = _script(script, f"hydra.run.dir={tmp_path}", *overrides)  # the lock went with its holder
    assert done.returncode == 0, done.stderr[-2000:]
    assert not (tmp_path / ".dipnet-run.lock.holder").exists()


# ----------------------------------------------------------------------------- sweep directories
def test_second_sweep_into_the_folder_of_a_first_is_refused(tmp_path, monkeypatch, capsys):
    """Before: both exited 0; job 0 of the first sweep was replaced by the second's, job 1 stayed, and the log
    said 'sweep finished: 2 of 2 jobs ok' after one job ran. The first sweep's own command runs again (so its
    checkpointed jobs can resume). The three sweeps run in this process (tests/script_runs.py: the same exit
    code and output, without the ~6 s each subprocess spent importing torch)."""
    def sweep_of(*overrides: str) -> subprocess.CompletedProcess:
        return run_script("reconstruct", "-m", *QUICK, *overrides, monkeypatch=monkeypatch, capsys=capsys)

    sweep = tmp_path / "sweep"
    first = sweep_of("seed=0,1", f"hydra.sweep.dir={sweep}")
    assert first.returncode == 0 and "sweep finished: 2 of 2 jobs ok" in first.stdout, first.stderr[-2000:]
    line = one_line_error(sweep_of("seed=2", f"hydra.sweep.dir={sweep}"))
    assert line == (f"error: hydra.sweep.dir={sweep} already holds another sweep (2 jobs): give this sweep another "
                    "hydra.sweep.dir, or delete that folder to run it again")
    assert [(r.status, r.config["seed"]) for r in collect_runs(sweep)] == [("ok", 0), ("ok", 1)]
    again = sweep_of("seed=0,1", f"hydra.sweep.dir={sweep}")  # the same sweep: its folder
    assert again.returncode == 0 and "sweep finished: 2 of 2 jobs ok" in again.stdout, again.stderr[-2000:]


# ----------------------------------------------------------------------------- damaged checkpoints
CHECKPOINTED = [*QUICK, "solver=voxel", "solver.iterations=20", "solver.tol=0", "output.checkpoint=true",
                "output.checkpoint_every=5", "threads=1"]
FINE = "voxel_16_3.pt"  # the fine stage's file (the coarse stage is voxel_8_3.pt)


def _reconstruct_in_process(monkeypatch, run_dir: Path, *overrides: str) -> dict:
    """``python scripts/reconstruct.py hydra.run.dir=<run_dir> ...`` in this process (tests/script_runs.py); its
    metrics."""
    done = run_script("reconstruct", f"hydra.run.dir={run_dir}", *CHECKPOINTED, *overrides, monkeypatch=monkeypatch,
                      capsys=None)
    assert done.returncode == 0, f"the job exited {done.returncode}"
    return json.loads((run_dir / "metrics.json").read_text())


@functools.cache
def _composed(overrides: tuple[str, ...]) -> DictConfig:
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[*CHECKPOINTED, *overrides])


def _rerun(run_dir: Path, *overrides: str) -> dict:
    """The job ``_reconstruct_in_process`` runs, as the script runs it (its ``locked_run``: the pipeline holding
    ``run_dir``) on the config Hydra composes from the same overrides; its metrics. Hydra's start-up (it composes
    the config twice, writes its log and config files) cost twice the job and is no part of what the reruns
    check: the checkpoint each stage finds. ``finished`` runs through the script's Hydra entry point."""
    load_script("reconstruct").locked_run(copy.deepcopy(_composed(overrides)), run_dir)
    return json.loads((run_dir / "metrics.json").read_text())


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A checkpointed job run to its end: its directory (checkpoints/ and metrics.json)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        run_dir = tmp_path_factory.mktemp("finished")
        _reconstruct_in_process(monkeypatch, run_dir)
    return run_dir


def _checkpoint_warnings(record) -> list[str]:
    return [str(w.message) for w in record if str(w.message).startswith("checkpoint ")]


class _RunsCode:
    """A pickle that would create a file when unpickled: a checkpoint must never be unpickled so."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return Path.touch, (self.marker,)


DAMAGE = {
    "truncated": lambda file: file.write_bytes(file.read_bytes()[: file.stat().st_size // 2]),
    "empty": lambda file: file.write_bytes(b""),
    "random bytes": lambda file: file.write_bytes(np.random.default_rng(0).bytes(5000)),
    "code in a pickle": lambda file: file.write_bytes(pickle.dumps(_RunsCode(file.with_name("pwned")))),
    "another job's file": lambda file: torch.save({"weights": torch.zeros(3)}, file),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_damaged_checkpoint_warns_once_and_its_stage_starts_afresh(finished, tmp_path, damage):
    """Before: EOFError, UnpicklingError or RuntimeError tracebacks on every rerun (and a pickle ran its code)."""
    shutil.copytree(finished / "checkpoints", tmp_path / "checkpoints")
    file = tmp_path / "checkpoints" / FINE
    DAMAGE[damage](file)
    with pytest.warns(UserWarning) as record:
        metrics = _rerun(tmp_path)
    [message] = _checkpoint_warnings(record)
    assert message.startswith(f"checkpoint {file} is not used: ") and message.endswith(
        "starting 'voxel 16^3' afresh"), message
    assert not (tmp_path / "checkpoints" / "pwned").exists()
    reference = json.loads((finished / "metrics.json").read_text())
    assert metrics["chamfer"] == pytest.approx(reference["chamfer"], rel=1e-4)
    assert torch.load(file, weights_only=True)["done"] is True  # rewritten whole


def test_checkpoint_of_another_operator_is_not_resumed(finished, tmp_path):
    """Same parameter shapes and data, another forward model: the saved state does not belong here."""
    shutil.copytree(finished / "checkpoints", tmp_path / "checkpoints")
    with pytest.warns(UserWarning) as record:
        _rerun(tmp_path, "operator=grid_sample")
    assert [m.split(" is not used: ")[1] for m in _checkpoint_warnings(record)] == [
        f"it was made for another problem (grid, operator, measured data or solver settings differ); "
        f"starting {stage!r} afresh" for stage in ("voxel 8^3", "voxel 16^3", "voxel 16^3 refit")]


def test_second_solve_into_a_busy_checkpoint_directory_is_refused(tmp_path, monkeypatch, capsys):
    """Before: two jobs with one explicit ``output.checkpoint=DIR`` (each in its own run directory) both solved,
    overwriting each other's checkpoints, and each ignored the other's on a resume."""
    shared = tmp_path / "shared"
    holder = HeldLock(shared / CHECKPOINT_LOCK_NAME)  # another job solving into it
    try:
        proc = run_script("reconstruct", f"hydra.run.dir={tmp_path / 'run'}", *CHECKPOINTED,
                          f"output.checkpoint={shared}", monkeypatch=monkeypatch, capsys=capsys)
    finally:
        holder.release()
    line = one_line_error(proc)
    assert re.match(rf"error: checkpoint directory {re.escape(str(shared))} is in use by another solve \(pid "
                    rf"{os.getpid()} on .+\): two solves checkpointing into one directory would overwrite each "
                    r"other's checkpoints; wait for it to finish, or give this job its own \(output\.checkpoint="
                    r"true: <run dir>/checkpoints\)$", line), line
    assert not list(shared.glob("*.pt"))  # refused before its first step
    metrics = _rerun(tmp_path / "run", f"output.checkpoint={shared}")  # the lock went with its holder
    assert metrics["chamfer"] < 0.1 and sorted(p.name for p in shared.glob("*.pt")) == [
        "voxel_16_3.pt", "voxel_16_3_refit.pt", "voxel_8_3.pt"]
    assert not (shared / f"{CHECKPOINT_LOCK_NAME}.holder").exists()


def test_stale_tmp_beside_a_checkpoint_is_harmless(finished, tmp_path):
    shutil.copytree(finished / "checkpoints", tmp_path / "checkpoints")
    (tmp_path / "checkpoints" / f"{FINE}.tmp").write_bytes(b"half a checkpoint")  # a kill mid-write
    with pytest.warns(UserWarning) as record:
        _rerun(tmp_path)
    assert _checkpoint_warnings(record) == []  # resumed from the finished stages
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [  # the lock file stays, empty
        ".dipnet-checkpoint.lock", "voxel_16_3.pt", "voxel_16_3_refit.pt", "voxel_8_3.pt"]  # refit: weight_rule's


def test_full_disk_during_a_checkpoint_write_warns_once_and_the_solve_goes_on(finished, tmp_path, monkeypatch):
    """Before: the RuntimeError of torch.save ended the job; its partial .tmp stayed."""
    real_save = torch.save

    def full_disk(obj, stream, *args, **kwargs):
        if stream.name.endswith(f"{FINE}.tmp"):
            stream.write(b"PK\x03\x04 the first bytes")
            raise RuntimeError("[enforce fail at inline_container.cc:783] . PytorchStreamWriter failed writing "
                               "file data/3: file write failed")
        return real_save(obj, stream, *args, **kwargs)

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.warns(UserWarning) as record:
        metrics = _rerun(tmp_path)
    [message] = _checkpoint_warnings(record)
    assert message.startswith(f"checkpoint {tmp_path / 'checkpoints' / FINE} could not be written (RuntimeError: ")
    assert message.endswith("the solve goes on, a rerun resumes from the previous checkpoint (if any)")
    # no partial file of the fine stage (the TV weight's refit after it saved its own)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [  # (the lock file stays, empty)
        ".dipnet-checkpoint.lock", "voxel_16_3_refit.pt", "voxel_8_3.pt"]
    reference = json.loads((finished / "metrics.json").read_text())
    assert metrics["chamfer"] == pytest.approx(reference["chamfer"], rel=1e-4)


# ----------------------------------------------------------------------------- scans: messages
@pytest.mark.slow
def test_refused_scan_resume_names_the_differing_fields_in_one_line(tmp_path):
    """Before: both full headers (~2,500 characters) and no word on what differs."""
    first = _script(SCAN, f"hydra.run.dir={tmp_path}", *QUICK_SCAN)
    assert first.returncode == 0, first.stderr[-2000:]
    line = one_line_error(_script(SCAN, f"hydra.run.dir={tmp_path}", *QUICK_SCAN, "protocol.step_mm=10",
                                   "rig.tank_cross_section_mm2=50000"))
    assert re.fullmatch(rf"error: {re.escape(str(tmp_path / 'rawscan.jsonl'))}: cannot resume, the new scan differs "
                        r"from the recorded one in tank_cross_section_mm2 20000\.0 -> 50000; step_mm 20\.0 -> "
                        r"10\.0 \(recorded -> new\): scan with the recorded settings, or into another file", line), line


FULL_DISK = """
import errno, runpy, sys
import dipnet.core.rawscan_writer

write, records = dipnet.core.rawscan_writer._write_all, []

def full_disk(fd, data):  # the disk fills after 8 records: every later write fails
    records.append(data)
    if len(records) > 8:
        raise OSError(errno.ENOSPC, "No space left on device")
    write(fd, data)

dipnet.core.rawscan_writer._write_all = full_disk
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


@pytest.mark.slow
def test_full_disk_during_a_scan_ends_in_the_safe_stop_message_alone(tmp_path):
    """Before: every log record the full disk refused printed a "--- Logging error ---" traceback."""
    proc = subprocess.run([sys.executable, "-c", FULL_DISK, str(SCAN), f"hydra.run.dir={tmp_path}", *QUICK_SCAN,
                           "hydra.job_logging.handlers.file.filename=/dev/full"],  # the log's disk is full too
                          capture_output=True, text=True, timeout=300)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 3 and len(lines) == 1, proc.stderr[-3000:]
    assert re.fullmatch(r"error: scan stopped at .+: OSError: \[Errno 28\] No space left on device; object lifted: "
                        r"the controller reports lower 0\.000 mm \(safe height 0 mm\); kept \d+ readings .+", lines[0])


def test_ctrl_c_between_an_adaptive_scans_batches_prints_one_line_and_how_to_resume(tmp_path, monkeypatch, capsys):
    """The runner stops a dip in progress safely itself (exit 3); a Ctrl-C outside it (an adaptive scan planning its
    next batch) printed a 105-line KeyboardInterrupt traceback and no way on. The script runs in this process
    (tests/script_runs.py); loaded afresh, it imports the patched scan job."""
    import dipnet.jobs.scan

    def planning(*args, **kwargs):  # Ctrl-C while an adaptive scan reconstructs to plan its next batch
        raise KeyboardInterrupt

    monkeypatch.setattr(dipnet.jobs.scan, "scan_job", planning)
    proc = run_script("scan", f"hydra.run.dir={tmp_path}", *QUICK_SCAN, monkeypatch=monkeypatch, capsys=capsys)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 130 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0] == "interrupted: scan stopped outside a dip (no dip was in progress): nothing was recorded yet"
