"""Issue 22, files and lost work: two jobs never share a run directory, damaged checkpoints never
block a rerun, a full disk never buries the safe-stop message. Each case runs the command as a
user would (a subprocess of the script)."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECONSTRUCT = ROOT / "scripts" / "reconstruct.py"
SCAN = ROOT / "scripts" / "scan.py"
QUICK = ["output.progress=false", "output.figures=false", "output.uncertainty=false",
         "output.resolvability=false", "resolution=16", "n_dips=12", "shape.name=ball"]
QUICK_SCAN = ["orientations.n=2", "protocol.step_mm=20", "fsync=false", "progress=false"]


def _script(script: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(script), *overrides], capture_output=True, text=True, timeout=300)


def _one_line_error(proc: subprocess.CompletedProcess) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    return lines[0]


@contextmanager
def _job_in(directory: Path) -> Iterator[int]:
    """Another process holding ``directory`` as a running job does; yields its pid."""
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from dipnet.locks import run_directory_lock\n"
                               f"with run_directory_lock({str(directory)!r}):\n"
                               "    print('held', flush=True); sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        yield holder.pid
    finally:
        holder.communicate("", timeout=60)


# ----------------------------------------------------------------------------- run directory lock
@pytest.mark.parametrize("script,overrides", [(RECONSTRUCT, QUICK), (SCAN, QUICK_SCAN)])
def test_second_job_into_a_busy_run_directory_is_refused(tmp_path, script, overrides):
    """Before: both jobs exited 0 saying "outputs written"; only the second one's files remained."""
    with _job_in(tmp_path) as pid:
        line = _one_line_error(_script(script, f"hydra.run.dir={tmp_path}", *overrides))
    assert re.match(rf"error: run directory {re.escape(str(tmp_path))} is in use by another job \(pid {pid} on "
                    r".+, since \d{4}-\d\d-\d\dT[\d:]+[+-]\d{4}\): wait for it to finish, stop it, or choose another "
                    r"output directory \(hydra\.run\.dir=\.\.\.\)$", line), line
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "rawscan.jsonl").exists()
    done = _script(script, f"hydra.run.dir={tmp_path}", *overrides)  # the lock went with its holder
    assert done.returncode == 0, done.stderr[-2000:]
    assert not (tmp_path / ".dipnet-run.lock.holder").exists()
