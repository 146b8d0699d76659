"""Shared scenes of the calibration tests: a reference ball dipped on a fake GRBL rig of known geometry, ideal ball
dips, a ball in a tank smaller than assumed and an off-axis ball on the grid plan of random rigs."""

from __future__ import annotations

import numpy as np

from dipnet.calibration.moments import dip_moments
from dipnet.core.geometry import RigGeometry
from dipnet.core.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.core.rawscan import ScanHeader
from dipnet.rig.fake.world import FakeRig
from dipnet.rig.grbl import GrblController
from dipnet.rig.runner import ScanPlan, ScanRunner, plan_orientations
from dipnet.rig.sensors import LineSensor
from dipnet.shapes import Ball
from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank, simulate_scan

AREA = 20000.0
RADIUS = 25.0
FAKE_TRUTH = RigGeometry(pivot_mm=20.0, tilt_axis_offset_mm=10.0, tilt_zero_deg=1.0, cross_section_mm2=0.95 * AREA)
MISMATCH = RigGeometry(pivot_mm=20.0, tilt_axis_offset_mm=15.0, tilt_zero_deg=1.0, cross_section_mm2=0.92 * 60000.0)


def scan_ball(path, plan_geometry: RigGeometry | None = None):
    """A reference ball dipped on a fake GRBL rig whose true geometry is FAKE_TRUTH; the runner is told
    ``plan_geometry`` (default: the ideal rig)."""
    world = FakeRig(Ball(RADIUS), tank=Tank(cross_section_mm2=AREA), origin_height_mm=40.0, geometry=FAKE_TRUTH,
                    level_quantum_mm=0.001, name="calibration-rig").register()
    plan = ScanPlan(plan_orientations("grid", tilts=[0.0, 25.0, 50.0, 70.0], spins=[0.0, 180.0]), start_mm=0.0,
                    stop_mm=95.0, step_mm=1.5, origin_height_mm=40.0, geometry=plan_geometry or RigGeometry())
    header = ScanHeader(quantity="level_mm", tank_cross_section_mm2=AREA, step_mm=plan.step_mm, resolution=0.001,
                        rig="fake-grbl", config={"tank_id": "tank-1"})
    ScanRunner(GrblController(world.url("grbl"), timeout=0.3, move_timeout=2.0),
               LineSensor(world.url("level"), pattern=r"L=(?P<value>[-+\d.]+)\s*(?P<unit>mm)"), plan, path, header,
               progress=False, fsync=False).run()
    return path


def ideal_ball_moments(geometry: RigGeometry, snr_db: float | None = None):
    raw = simulate_scan(Ball(30.0), fibonacci_hemisphere(60), tank=Tank(60000.0), geometry=geometry,
                        sensor=LevelSensor(snr_db=snr_db, seed=3), progress=False)
    return raw, dip_moments(raw, RigGeometry())


def ball_in_smaller_tank():
    """24 dips of a ball (r 25 mm) in a tank 8 % smaller than the 60,000 mm^2 the scan assumes; 40 dB."""
    return simulate_scan(Ball(25.0), fibonacci_hemisphere(24), tank=Tank(60000.0), sensor=LevelSensor(snr_db=40.0),
                         geometry=RigGeometry(cross_section_mm2=0.92 * 60000.0), protocol=DipProtocol(step_mm=1.0),
                         progress=False)


def grid_ball_scans(seeds):
    """A 30 mm ball 25 mm off the spin axis dipped on the documented 16-dip grid plan (tilts 0/25/50/70 deg x spins
    0/90/180/270 deg; tilt 0 a hair above 0 so that its spins stay four dips) at 30 dB, one rig per seed drawn over
    the calibrated range (pivot +-60 mm, offset +-40 mm, zeros +-5 deg, step scale and section +-3 % and +-20 %):
    ``[(true geometry, raw scan)]``."""
    tilts, spins = [1e-6, 25.0, 50.0, 70.0], [0.0, 90.0, 180.0, 270.0]
    directions = rig_to_direction([t for t in tilts for _ in spins], [s for _ in tilts for s in spins])
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        true = RigGeometry(pivot_mm=rng.uniform(-60, 60), tilt_axis_offset_mm=rng.uniform(-40, 40),
                           tilt_zero_deg=rng.uniform(-5, 5), spin_zero_deg=rng.uniform(-5, 5),
                           step_scale=1 + rng.uniform(-0.03, 0.03), cross_section_mm2=60000.0 * rng.uniform(0.8, 1.2))
        out.append((true, simulate_scan(Ball(30.0, center=(25.0, 0.0, 0.0)), directions, tank=Tank(60000.0),
                                        geometry=true, sensor=LevelSensor(snr_db=30.0, seed=seed), progress=False)))
    return out



#: A level drift over a small object's rise (a hammer): 1.4 mm over its 13-hour session of 100
#: dips, where the hammer (2,000 mm^3 in an 84,000 mm^2 tank) rises the level by 0.024 mm.
DRIFTING = RigGeometry(pivot_mm=-120.0, tilt_axis_offset_mm=30.0, tilt_zero_deg=-8.0, level_drift_mm_per_s=-3e-5)


def drifting_hammer_scan(n_dips: int):
    """The bundled hammer (radius 40 mm) dipped ``n_dips`` times at 30 dB on the rig :data:`DRIFTING`."""
    from dipnet.preprocessing.datasets import mesh_path
    from dipnet.shapes import load_mesh

    return simulate_scan(load_mesh(mesh_path("hammer"), radius=40.0), fibonacci_hemisphere(n_dips),
                         tank=Tank(84000.0), geometry=DRIFTING, sensor=LevelSensor(snr_db=30.0, seed=1), progress=False)
