"""Every gallery script in examples/ runs as a user would run it and writes what its page says."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.seen_first]

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
# what each example must leave in the output directory it is given (a new example must be listed here)
WRITES = {
    "quickstart": ["dips.npz"],
    "own_mesh": ["part_cm.stl", "run/metrics.json", "run/reconstruction.ply", "run/mesh.png"],
    "three_cats": ["metrics.json", "reconstruction.ply"],
    "fake_rig_scan": ["rawscan.jsonl", "reconstruction/metrics.json"],
    "reference_ball": ["ball.jsonl", "rig_calibration.yaml"],
    "adaptive_planning": ["planning.json", "metrics.json"],
    "sweep_and_compare": ["sweep/compare/summary.md", "sweep/compare/runs.csv", "sweep/compare/vs_dips.png"],
}


def test_every_example_is_listed():
    assert sorted(p.stem for p in EXAMPLES.glob("*.py")) == sorted(WRITES)


@pytest.mark.parametrize("name", sorted(WRITES))
def test_example_runs(name, tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    done = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), str(out)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip(), "an example prints what it found"
    missing = [f for f in WRITES[name] if not (out / f).is_file()]
    assert not missing, missing
