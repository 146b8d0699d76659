"""dipnet.experiments.random_rigs: the calibration benchmarks' random rigs stay in the calibrated range, and a
report's coverage counts only what it determines."""

from __future__ import annotations

import numpy as np

from dipnet.calibration.model import CalibrationReport
from dipnet.experiments.random_rigs import covered, draw_rig


def test_rigs_are_drawn_over_the_calibrated_range_and_by_seed():
    rigs = [draw_rig(np.random.default_rng(seed), 60000.0, 3600.0) for seed in range(200)]
    bounds = {"pivot_mm": 60.0, "tilt_axis_offset_mm": 40.0, "tilt_zero_deg": 5.0, "spin_zero_deg": 5.0}
    for name, bound in bounds.items():
        values = np.array([getattr(r, name) for r in rigs])
        assert np.abs(values).max() <= bound and np.abs(values).max() > 0.9 * bound, name
    steps = np.array([r.step_scale for r in rigs])
    sections = np.array([r.cross_section_mm2 for r in rigs]) / 60000.0
    drifts = np.array([r.level_drift_mm_per_s for r in rigs]) * 3600.0  # mm over the session
    lags = np.array([r.sensor_lag_s for r in rigs])
    assert np.abs(steps - 1).max() <= 0.03 and np.abs(sections - 1).max() <= 0.2
    assert np.abs(drifts).max() <= 0.5 and 0.0 <= lags.min() and lags.max() <= 0.5
    assert draw_rig(np.random.default_rng(7), 60000.0, 3600.0) == draw_rig(np.random.default_rng(7), 60000.0, 3600.0)


def test_coverage_counts_the_determined_parameters_only():
    report = CalibrationReport(estimates={"pivot_mm": 1.0, "tilt_zero_deg": 0.2, "spin_zero_deg": 0.0},
                               standard_errors={"pivot_mm": 0.5, "tilt_zero_deg": 0.1, "spin_zero_deg": 1.0},
                               correlations={}, undetermined={"spin_zero_deg": "symmetric"},
                               intervals={"pivot_mm": (0.2, 1.8), "tilt_zero_deg": (0.05, 0.35),
                                          "spin_zero_deg": (-2.0, 2.0)})
    truth = {"pivot_mm": 1.5, "tilt_zero_deg": 0.5, "spin_zero_deg": 3.0}
    assert covered(report, truth) == [("pivot_mm", True), ("tilt_zero_deg", False)]
    assert covered(report, {"pivot_mm": 1.5}) == [("pivot_mm", True)]  # a parameter without a truth is not counted

