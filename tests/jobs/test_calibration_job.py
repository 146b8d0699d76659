"""The calibration job (dipnet.jobs.calibration_job): what a self-calibration step writes into the run directory
and hands on (a stand-in calibrator on a simulated scan), and calibration=self end to end (slow)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch

from dipnet.calibration.model import CalibrationReport
from dipnet.core.calibration_file import TANK_CONFIG_KEY, load_calibration
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.jobs.calibration_job import self_calibration_job
from dipnet.operators import make_operator
from dipnet.preprocessing.preprocess import preprocess
from dipnet.preprocessing.sources import Recording
from dipnet.shapes import Ball
from dipnet.simulator.physics import Tank, simulate_scan


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


class StandInCalibrator:
    """A calibrator that returns a fixed result (the job's contract, not the fit, is under test)."""

    def __init__(self, result, tank=None):
        self.result, self.tank, self.calls = result, tank, []

    def run(self, recording, grid, solver, n_slabs, operator_factory):
        self.calls.append((recording, grid, solver, n_slabs))
        return self.result


@pytest.mark.parametrize("tank,expected", [(None, "tank-7"), ("tank-9", "tank-9")])
def test_the_job_writes_the_calibration_the_report_and_the_measurement(tmp_path, tank, expected):
    raw = simulate_scan(Ball(25.0), fibonacci_hemisphere(4), tank=Tank(60000.0), progress=False)
    raw.header.config[TANK_CONFIG_KEY] = "tank-7"
    grid = Grid(16, extent=80.0)
    measurement = preprocess(raw, grid=grid, t_start="metadata")
    report = CalibrationReport(estimates={"pivot_mm": 3.0}, standard_errors={"pivot_mm": 0.2}, correlations={},
                               intervals={"pivot_mm": (2.7, 3.3)})
    result = SimpleNamespace(geometry=RigGeometry(pivot_mm=3.0), report=report, history=[{"step": 0, "gain": 1.0}],
                             t0_mm=0.5, measurement=measurement, reconstruction="the reconstruction")
    calibrator = StandInCalibrator(result, tank)
    built = []

    def factory(g, directions, n_slabs):
        built.append((g, n_slabs))
        return make_operator(g, directions, n_slabs)

    m, operator, recon = self_calibration_job(calibrator, Recording(raw), grid, "a solver", 16, factory, tmp_path)
    assert m is measurement and recon == "the reconstruction" and built == [(grid, 16)]
    assert torch.equal(operator.directions, measurement.directions.double())
    assert calibrator.calls == [(Recording(raw), grid, "a solver", 16)]
    cal = load_calibration(tmp_path / "rig_calibration.yaml")
    assert (cal.geometry.pivot_mm, cal.tank, cal.method) == (3.0, expected, "self")
    assert cal.intervals == {"pivot_mm": (2.7, 3.3)}
    assert cal.notes == "self-calibration of a simulated scan"
    written = json.loads((tmp_path / "self_calibration.json").read_text())
    assert written["history"] == [{"step": 0, "gain": 1.0}] and written["t0_mm"] == 0.5
    assert written["estimates"] == {"pivot_mm": 3.0} and written["intervals_90"] == {"pivot_mm": [2.7, 3.3]}
    saved = DipMeasurement.load(tmp_path / "measurement.npz")
    assert torch.allclose(saved.profiles, measurement.profiles)
