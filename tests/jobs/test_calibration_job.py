"""The calibration job (dipnet.jobs.calibration_job): calibration=self in a reconstruction run."""

from __future__ import annotations

import pytest

from dipnet.core.calibration_file import load_calibration


@pytest.mark.slow
def test_the_command_line_calibrates_a_rig_far_from_nominal(tmp_path):
    """The issue's case: start heights tens of mm off at high tilt. Nothing validates with the nominal
    geometry before the calibration ran; the run writes a calibration file that says what it holds."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parents[2] / "scripts" / "reconstruct.py"
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, str(script), "calibration=self", "resolution=16", "n_dips=40",
                           "solver=voxel", "solver.iterations=30", "output.figures=false", "output.resolvability=false",
                           "source.simulator.geometry={pivot_mm: 50.0, tilt_axis_offset_mm: -30.0, tilt_zero_deg: 2.0}",
                           f"hydra.run.dir={out}"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    cal = load_calibration(out / "rig_calibration.yaml")
    assert cal.method == "self"
    assert cal.geometry.pivot_mm == pytest.approx(50.0, abs=2.0)
    assert cal.geometry.tilt_axis_offset_mm == pytest.approx(-30.0, abs=2.0)
    assert {"spin_zero_deg", "step_scale", "sensor_lag_s"} <= set(cal.not_estimated)
    assert "pivot_mm" in cal.intervals and "spin_zero_deg" not in cal.intervals
