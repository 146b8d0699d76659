"""Calibration: a reference ball on a mismatched fake rig, self-calibration, identifiability warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from dipnet.calibration import CalibrationError, ProfileModel, State, calibrate_reference, identifiability, \
    self_calibrate
from dipnet.grid import Grid
from dipnet.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.physics import DipProtocol, LevelSensor, Tank, simulate_scan
from dipnet.rawscan import ScanHeader
from dipnet.rig.calibration_file import Calibration, load_calibration, save_calibration
from dipnet.rig.fake import FakeRig
from dipnet.rig.geometry import RigGeometry
from dipnet.rig.grbl import GrblController
from dipnet.rig.recorded import read_recorded
from dipnet.rig.runner import ScanPlan, ScanRunner, plan_orientations
from dipnet.rig.sensors import LineSensor
from dipnet.shapes import Ball, Box
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver

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


@pytest.fixture(scope="module")
def ball_scan(tmp_path_factory):
    return scan_ball(tmp_path_factory.mktemp("ball") / "ball.jsonl")


def test_reference_ball_recovers_the_fake_rigs_geometry(ball_scan, tmp_path):
    """scripts/calibrate.py end to end: the file it writes holds the fake rig's true geometry, and a
    reader using that file places the ball's profiles where an ideal rig would have."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("calibrate", Path(__file__).parents[1] / "scripts" / "calibrate.py")
    calibrate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(calibrate)
    out = tmp_path / "rig_calibration.yaml"
    assert calibrate.main([str(ball_scan), "--ball-radius", str(RADIUS), "--n", "64", "--output", str(out)]) == 0
    g = load_calibration(out, rig="fake-grbl", tank="tank-1").geometry
    assert g.pivot_mm == pytest.approx(20.0, abs=1.0) and g.tilt_axis_offset_mm == pytest.approx(10.0, abs=0.5)
    assert g.tilt_zero_deg == pytest.approx(1.0, abs=0.2) and g.cross_section_mm2 == pytest.approx(0.95 * AREA, rel=0.005)
    grid = Grid(32, extent=80.0)
    ideal = Ball(RADIUS).occupancy(grid, supersample=3).sum().item() * grid.voxel_volume
    for source in ({"calibration": out}, {}):
        m = read_recorded(ball_scan, grid, smooth=False, **source)
        centroids = (m.profiles.numpy() @ (np.arange(32) + 0.5 - 16) * grid.voxel_size) / m.profiles.sum(1).numpy()
        if source:  # a ball at the origin: every profile centred on 0 and holding its volume
            assert np.abs(centroids).max() < 0.3 and m.volume_estimate() == pytest.approx(ideal, rel=0.01)
        else:  # the uncalibrated reader misplaces the tilted dips by millimetres
            assert np.abs(centroids).max() > 3.0


def test_reference_calibration_refuses_the_wrong_object(ball_scan):
    from dipnet.rawscan import read_rawscan

    with pytest.raises(CalibrationError, match="does not fit the dips"):
        calibrate_reference(read_rawscan(ball_scan), Ball(0.8 * RADIUS), Grid(32, extent=80.0),
                            ("pivot_mm", "tilt_axis_offset_mm"))


def test_self_calibration_recovers_pivot_offset_and_tilt_zero():
    """The bench's mismatch on a small noisy problem: heights and directions come back; the
    cross-section is found degenerate with the shape's own dilation, named, and kept."""
    shape = Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0))
    raw = simulate_scan(shape, fibonacci_hemisphere(40), tank=Tank(60000.0), sensor=LevelSensor(snr_db=30.0),
                        geometry=MISMATCH, protocol=DipProtocol(step_mm=1.0), progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = self_calibrate(raw, Grid(24, extent=100.0), VoxelSolver(iterations=60, progress=False, seed=0),
                                iterations=1)
    g, report = result.geometry, result.report
    assert g.pivot_mm == pytest.approx(20.0, abs=1.0) and g.tilt_axis_offset_mm == pytest.approx(15.0, abs=1.0)
    assert g.tilt_zero_deg == pytest.approx(1.0, abs=0.3)
    assert report.standard_errors["pivot_mm"] < 1.0
    assert abs(g.pivot_mm - 20.0) < 4 * report.standard_errors["pivot_mm"] + 0.3  # the error bars mean something
    assert set(report.undetermined) == {"cross_section_mm2"} and "dilate_mm" in report.undetermined["cross_section_mm2"]
    assert g.cross_section_mm2 is None and report.estimates["cross_section_mm2"] == 60000.0  # kept, not guessed


def test_small_tilts_warn_naming_the_parameters():
    """Tilts of at most 10 deg: the pivot barely moves a dip (p (cos r - 1) < 0.02 p), and the spin zero
    offset is the object's own rotation: both are named, and self-calibration keeps them at their start."""
    tilts, spins = np.meshgrid([0.0, 5.0, 10.0], [0.0, 90.0, 180.0, 270.0])
    raw = simulate_scan(Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0)), rig_to_direction(tilts.ravel(), spins.ravel()),
                        sensor=LevelSensor(snr_db=30.0), progress=False)
    params = ("pivot_mm", "tilt_axis_offset_mm", "spin_zero_deg")
    report = identifiability(ProfileModel(raw, Grid(24, extent=100.0)), None, State(RigGeometry()), params)
    assert set(report.undetermined) >= {"pivot_mm", "spin_zero_deg"}
    assert "rotation or position" in report.undetermined["spin_zero_deg"]
    with pytest.warns(UserWarning, match="pivot_mm is not identifiable"):
        result = self_calibrate(raw, Grid(24, extent=100.0), MinNormSolver(progress=False), params)
    assert result.geometry.pivot_mm == 0.0 and result.geometry.spin_zero_deg == 0.0


def test_a_scan_with_the_calibration_reads_right(tmp_path):
    """A scan run with the calibrated geometry records its start heights with it (and the geometry in its
    header); the reader given the same file adds only what the runner did not: no height is shifted twice."""
    cal = Calibration(FAKE_TRUTH, rig="fake-grbl", tank="tank-1")
    file = save_calibration(cal, tmp_path / "cal.yaml")
    path = scan_ball(tmp_path / "calibrated.jsonl", FAKE_TRUTH)
    grid = Grid(32, extent=80.0)
    m = read_recorded(path, grid, smooth=False, calibration=file)
    centroids = (m.profiles.numpy() @ (np.arange(32) + 0.5 - 16) * grid.voxel_size) / m.profiles.sum(1).numpy()
    assert np.abs(centroids).max() < 0.3
    assert m.volume_estimate() == pytest.approx(Ball(RADIUS).volume, rel=0.01)


def ball_in_smaller_tank():
    """24 dips of a ball (r 25 mm) in a tank 8 % smaller than the 60,000 mm^2 the scan assumes; 40 dB."""
    return simulate_scan(Ball(25.0), fibonacci_hemisphere(24), tank=Tank(60000.0), sensor=LevelSensor(snr_db=40.0),
                         geometry=RigGeometry(cross_section_mm2=0.92 * 60000.0), protocol=DipProtocol(step_mm=1.0),
                         progress=False)


def test_self_calibration_finds_the_cross_section_with_the_shape():
    """Only the tank is wrong (8 % smaller than assumed): the joint shape + gain step recovers its
    cross-section within 3 % from a ball, and reports it determined."""
    raw = ball_in_smaller_tank()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = self_calibrate(raw, Grid(32, extent=80.0), VoxelSolver(iterations=150, progress=False),
                                ("cross_section_mm2",))
    assert result.geometry.cross_section_mm2 == pytest.approx(0.92 * 60000.0, rel=0.03)
    assert "cross_section_mm2" not in result.report.undetermined
    assert result.history[-1]["gain"] == pytest.approx(1 / 0.92, rel=0.03)
    assert "reference object" in result.report.caveats["cross_section_mm2"]


def test_the_cross_section_needs_a_solver_that_fits_a_gain():
    raw = simulate_scan(Ball(25.0), fibonacci_hemisphere(6), tank=Tank(60000.0), progress=False)
    with pytest.raises(CalibrationError, match="MinNormSolver cannot fit it"):
        self_calibrate(raw, Grid(16, extent=80.0), MinNormSolver(progress=False), ("cross_section_mm2",))


def test_the_gain_step_can_use_another_solver():
    """``gain_solver`` fits the cross-section (here the implicit field); the final shape is ``solver``'s."""
    raw = ball_in_smaller_tank()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = self_calibrate(raw, Grid(24, extent=80.0), VoxelSolver(iterations=60, progress=False),
                                ("cross_section_mm2",), gain_solver=ImplicitSolver(iterations=150, progress=False))
    assert result.geometry.cross_section_mm2 == pytest.approx(0.92 * 60000.0, rel=0.03)
    assert result.reconstruction.info["solver"] == "voxel"


def test_an_implausible_cross_section_is_named_and_kept():
    """A section further from the assumed one than ``max_section_change`` is not trusted: named
    undetermined (with the cause) and kept at the start."""
    raw = ball_in_smaller_tank()
    with pytest.warns(UserWarning, match="cross_section_mm2 is not identifiable.*more than max_section_change 2%"):
        result = self_calibrate(raw, Grid(24, extent=80.0), VoxelSolver(iterations=60, progress=False),
                                ("cross_section_mm2",), max_section_change=0.02)
    assert result.geometry.cross_section_mm2 is None and result.report.estimates["cross_section_mm2"] == 60000.0
    with pytest.raises(CalibrationError, match="max_section_change must be positive"):
        self_calibrate(raw, Grid(16, extent=80.0), VoxelSolver(progress=False), ("cross_section_mm2",),
                       max_section_change=0.0)
