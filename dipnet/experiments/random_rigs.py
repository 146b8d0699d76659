"""Random rigs and reference balls for the calibration benchmarks (``scripts/bench_calibration.py``,
``scripts/bench_reference_plans.py``): rig geometries drawn over the calibrated range, a 30 mm ball held off its
assumed place and start height, and whether a report's 90 % intervals hold the truth."""

from __future__ import annotations

import numpy as np

from dipnet.calibration.model import CalibrationReport
from dipnet.calibration.reference import calibrate_reference
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.shapes import Ball
from dipnet.simulator.physics import simulate_scan

BALL_RADIUS = 30.0  # the reference ball's radius (mm)
BALL_POSITION_SD_MM = 0.3  # how far off its assumed position the ball is held (normal standard deviation per axis)
START_HEIGHT_SD_MM = 0.3  # how far off the water line the ball's recorded stage zero is (normal standard deviation)


def draw_rig(rng: np.random.Generator, area: float, session_s: float) -> RigGeometry:
    """One rig geometry drawn uniformly over the calibrated range: pivot +-60 mm, tilt-axis offset +-40 mm, tilt
    and spin zeros +-5 deg, step scale +-3 %, cross-section ``area`` (mm^2) +-20 %, a level drift of up to +-0.5
    mm over a session of ``session_s`` seconds and a sensor lag of 0-0.5 s."""
    return RigGeometry(pivot_mm=rng.uniform(-60, 60), tilt_axis_offset_mm=rng.uniform(-40, 40),
                       tilt_zero_deg=rng.uniform(-5, 5), spin_zero_deg=rng.uniform(-5, 5),
                       step_scale=1 + rng.uniform(-0.03, 0.03), cross_section_mm2=area * (1 + rng.uniform(-0.2, 0.2)),
                       level_drift_mm_per_s=rng.uniform(-0.5, 0.5) / session_s, sensor_lag_s=rng.uniform(0.0, 0.5))


def reference_ball(offset_mm: float, held_at: tuple[float, float, float], raw_kwargs: dict, seed: int,
                   start_error_mm: float = 0.0) -> tuple[RigGeometry, CalibrationReport]:
    """``(geometry, report)``: the reference calibration from a ball assumed at ``(offset_mm, 0, 0)`` and
    dipped at ``held_at`` (mm, object frame) with :func:`simulate_scan`'s ``raw_kwargs``, its recorded start
    height ``start_error_mm`` off the true one."""
    raw = simulate_scan(Ball(BALL_RADIUS, center=held_at), progress=False, **raw_kwargs)
    raw.header.t_start_mm += start_error_mm
    grid = Grid(48, 3, extent=2.0 * (BALL_RADIUS + offset_mm) + 20.0)
    return calibrate_reference(raw, Ball(BALL_RADIUS, center=(offset_mm, 0.0, 0.0)), grid, seed=seed)


def covered(report: CalibrationReport, truth: dict[str, float]) -> list[tuple[str, bool]]:
    """(parameter, whether its 90% interval holds the truth) for every determined parameter."""
    out = []
    for name in report.determined:
        if name in truth:
            low, high = report.intervals[name]
            out.append((name, bool(low <= truth[name] <= high)))
    return out
