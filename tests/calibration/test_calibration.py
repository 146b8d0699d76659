"""Calibration: a reference ball on a mismatched fake rig, self-calibration, identifiability warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from dipnet.calibration.model import CalibrationError, to_calibration
from dipnet.calibration.reference import calibrate_reference
from dipnet.calibration.self_calibration import self_calibrate
from dipnet.calibration.moments import KnownObject, dip_moments, fit_drift, fit_moments
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank, simulate_scan
from dipnet.core.rawscan import ScanHeader
from dipnet.core.calibration_file import Calibration, load_calibration, save_calibration
from dipnet.rig.fake.world import FakeRig
from dipnet.core.geometry import RigGeometry
from dipnet.rig.grbl import GrblController
from dipnet.preprocessing.recorded import read_raw_recording
from dipnet.rig.runner import ScanPlan, ScanRunner, plan_orientations
from dipnet.rig.sensors import LineSensor
from dipnet.shapes import Ball, Box
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver
from script_modules import load_script

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
    calibrate = load_script("calibrate")
    out = tmp_path / "rig_calibration.yaml"
    assert calibrate.main([str(ball_scan), "--ball-radius", str(RADIUS), "--n", "64", "--output", str(out)]) == 0
    cal = load_calibration(out, rig="fake-grbl", tank="tank-1")
    g = cal.geometry
    assert g.pivot_mm == pytest.approx(20.0, abs=1.0) and g.tilt_axis_offset_mm == pytest.approx(10.0, abs=0.5)
    assert g.tilt_zero_deg == pytest.approx(1.0, abs=0.3) and g.cross_section_mm2 == pytest.approx(0.95 * AREA, rel=0.005)
    for name in ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "cross_section_mm2", "step_scale"):
        low, high = cal.intervals[name]
        assert low <= getattr(FAKE_TRUTH, name) <= high, name  # 8 dips: the intervals hold the truth
    assert {"spin_zero_deg", "sensor_lag_s"} <= set(cal.not_estimated)  # a centred ball's symmetry; never
    grid = Grid(32, extent=80.0)
    ideal = Ball(RADIUS).occupancy(grid, supersample=3).sum().item() * grid.voxel_volume
    for source in ({"calibration": out}, {}):
        m = read_raw_recording(ball_scan, grid, smooth=False, **source)
        centroids = (m.profiles.numpy() @ (np.arange(32) + 0.5 - 16) * grid.voxel_size) / m.profiles.sum(1).numpy()
        if source:  # a ball at the origin: every profile centred on 0 and holding its volume
            assert np.abs(centroids).max() < 0.3 and m.volume_estimate() == pytest.approx(ideal, rel=0.01)
        else:  # the uncalibrated reader misplaces the tilted dips by millimetres
            assert np.abs(centroids).max() > 3.0


def test_reference_calibration_refuses_the_wrong_object(ball_scan):
    from dipnet.core.rawscan import read_rawscan

    with pytest.raises(CalibrationError, match="does not fit the dips"):
        calibrate_reference(read_rawscan(ball_scan), Ball(0.8 * RADIUS), Grid(32, extent=80.0),
                            ("pivot_mm", "tilt_axis_offset_mm"))


def test_self_calibration_recovers_pivot_offset_and_tilt_zero():
    """The bench's mismatch on a small noisy problem: heights and directions come back inside their 90%
    intervals; the spin zero and step scale, gauges of an unknown object, are named and kept."""
    shape = Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0))
    raw = simulate_scan(shape, fibonacci_hemisphere(40), tank=Tank(60000.0), sensor=LevelSensor(snr_db=30.0),
                        geometry=MISMATCH, protocol=DipProtocol(step_mm=1.0), progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = self_calibrate(raw, Grid(24, extent=100.0), VoxelSolver(iterations=60, progress=False, seed=0),
                                ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale"))
    g, report = result.geometry, result.report
    assert g.pivot_mm == pytest.approx(20.0, abs=0.5) and g.tilt_axis_offset_mm == pytest.approx(15.0, abs=0.5)
    assert g.tilt_zero_deg == pytest.approx(1.0, abs=0.3)
    for name, true in (("pivot_mm", 20.0), ("tilt_axis_offset_mm", 15.0), ("tilt_zero_deg", 1.0)):
        low, high = report.intervals[name]
        assert low <= true <= high and name in report.determined  # the error bars hold the truth
    assert set(report.undetermined) == {"spin_zero_deg", "step_scale"}
    assert "rotation about the spin axis" in report.undetermined["spin_zero_deg"]
    assert "scale of the whole scene" in report.undetermined["step_scale"]
    assert "mm at the object's radius" in report.shape_motion["step_scale"]
    assert g.spin_zero_deg == 0.0 and g.step_scale == 1.0  # kept, not guessed


def test_small_tilts_leave_the_pivot_undetermined():
    """Tilts of at most 10 deg: the pivot barely moves a dip (p (cos r - 1) < 0.02 p): named, with a
    warning, and kept at its start, as is the spin zero (the object's own rotation)."""
    tilts, spins = np.meshgrid([0.0, 5.0, 10.0], [0.0, 90.0, 180.0, 270.0])
    raw = simulate_scan(Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0)), rig_to_direction(tilts.ravel(), spins.ravel()),
                        sensor=LevelSensor(snr_db=30.0), progress=False)
    params = ("pivot_mm", "tilt_axis_offset_mm", "spin_zero_deg")
    with pytest.warns(UserWarning, match="pivot_mm is not determined"):
        result = self_calibrate(raw, Grid(24, extent=100.0), MinNormSolver(progress=False), params)
    assert set(result.report.undetermined) >= {"pivot_mm", "spin_zero_deg"}
    assert result.geometry.pivot_mm == 0.0 and result.geometry.spin_zero_deg == 0.0


def ideal_ball_moments(geometry: RigGeometry, snr_db: float | None = None):
    raw = simulate_scan(Ball(30.0), fibonacci_hemisphere(60), tank=Tank(60000.0), geometry=geometry,
                        sensor=LevelSensor(snr_db=snr_db, seed=3), progress=False)
    return raw, dip_moments(raw, RigGeometry())


def test_ball_moments_give_the_exact_geometry():
    """Noise-free dips of a ball: its first two moments (centroid 0, variance R^2 / 5 along every
    direction) give pivot, offset, tilt zero and step scale exactly, and its volume the section."""
    true = RigGeometry(pivot_mm=-45.0, tilt_axis_offset_mm=30.0, tilt_zero_deg=-3.0, step_scale=1.025,
                       cross_section_mm2=52000.0)
    raw, moments = ideal_ball_moments(true)
    fit = fit_moments(moments, ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "step_scale"),
                      known=KnownObject.ball(30.0), bootstrap=0)
    assert fit.values["pivot_mm"] == pytest.approx(-45.0, abs=0.05)
    assert fit.values["tilt_axis_offset_mm"] == pytest.approx(30.0, abs=0.05)
    assert fit.values["tilt_zero_deg"] == pytest.approx(-3.0, abs=0.1)
    assert fit.values["step_scale"] == pytest.approx(1.025, abs=3e-4)
    assert KnownObject.ball(30.0).volume / moments.rise.mean() == pytest.approx(52000.0, rel=1e-3)


def test_a_centred_ball_on_an_ideal_rig_cannot_show_a_tilt_zero(tmp_path):
    """The issue's case: with pivot and offset 0 a centred ball's dips do not depend on the tilt zero (nor
    ever on the spin zero): both named, kept at 0 and written under not_estimated, not as estimates."""
    raw, _ = ideal_ball_moments(RigGeometry())
    with pytest.warns(UserWarning, match="tilt_zero_deg is not determined"):
        geometry, report = calibrate_reference(raw, Ball(30.0), Grid(32, extent=80.0))
    assert {"tilt_zero_deg", "spin_zero_deg"} <= set(report.undetermined)
    assert "symmetry" in report.undetermined["spin_zero_deg"]
    assert geometry.tilt_zero_deg == 0.0 and geometry.spin_zero_deg == 0.0
    assert geometry.step_scale == pytest.approx(1.0, abs=1e-3)
    path = save_calibration(to_calibration(geometry, report, "sim", "tank"), tmp_path / "cal.yaml")
    loaded = load_calibration(path)
    assert {"tilt_zero_deg", "spin_zero_deg", "sensor_lag_s"} <= set(loaded.not_estimated)
    assert "tilt_zero_deg" not in loaded.intervals and "pivot_mm" in loaded.intervals


def test_drift_is_read_from_the_rest_level():
    """A level drift of 0.5 mm over the session: the rest level before every dip's contact gives it."""
    true = RigGeometry(level_drift_mm_per_s=2e-5)
    raw, _ = ideal_ball_moments(true, snr_db=30.0)
    drift, (low, high) = fit_drift(raw)
    assert drift == pytest.approx(2e-5, rel=0.02) and low <= 2e-5 <= high


def test_a_scan_with_the_calibration_reads_right(tmp_path):
    """A scan run with the calibrated geometry records its start heights with it (and the geometry in its
    header); the reader given the same file adds only what the runner did not: no height is shifted twice."""
    cal = Calibration(FAKE_TRUTH, rig="fake-grbl", tank="tank-1")
    file = save_calibration(cal, tmp_path / "cal.yaml")
    path = scan_ball(tmp_path / "calibrated.jsonl", FAKE_TRUTH)
    grid = Grid(32, extent=80.0)
    m = read_raw_recording(path, grid, smooth=False, calibration=file)
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
    with pytest.warns(UserWarning, match="cross_section_mm2 is not determined.*more than max_section_change 2%"):
        result = self_calibrate(raw, Grid(24, extent=80.0), VoxelSolver(iterations=60, progress=False),
                                ("cross_section_mm2",), max_section_change=0.02)
    assert result.geometry.cross_section_mm2 is None and result.report.estimates["cross_section_mm2"] == 60000.0
    with pytest.raises(CalibrationError, match="max_section_change must be positive"):
        self_calibrate(raw, Grid(16, extent=80.0), VoxelSolver(progress=False), ("cross_section_mm2",),
                       max_section_change=0.0)


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


def test_a_solver_given_dips_that_share_no_voxel_says_so():
    """Profiles that put the object in two places at once (up: 20-25 mm above the centre; down: 20-25 mm
    below it, as far-off start heights do): the support hull is empty; one named error, no ZeroDivisionError."""
    from dipnet.core.measurement import DipMeasurement
    from dipnet.operators import make_operator
    from dipnet.solvers.optimize import EmptySupportError

    grid = Grid(16, extent=60.0)
    profiles = np.zeros((2, 16))
    profiles[:, 13:15] = 100.0  # slabs at 22.5-30 mm along each direction
    m = DipMeasurement(directions=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), profiles=profiles,
                       slab_thickness=grid.voxel_size, offsets=np.full(2, -30.0))
    with pytest.raises(EmptySupportError, match="calibrate the rig geometry"):
        VoxelSolver(iterations=5, progress=False).solve(m, make_operator(grid, m.directions, grid.n))


def test_calibrate_script_on_a_rig_far_from_nominal(tmp_path):
    """The issue's refusal: start heights ~50 mm off at 70 deg of tilt made scripts/calibrate.py say the ball
    'does not fit'. At the range's edges (pivot 55 mm, offset -35 mm, tilt zero 4 deg, step +2 %, section -15 %)
    the script now calibrates, and the file holds the truth inside its intervals."""
    true = RigGeometry(pivot_mm=55.0, tilt_axis_offset_mm=-35.0, tilt_zero_deg=4.0, step_scale=1.02,
                       cross_section_mm2=0.85 * 60000.0)
    raw = simulate_scan(Ball(30.0), fibonacci_hemisphere(60), tank=Tank(60000.0), geometry=true,
                        sensor=LevelSensor(snr_db=30.0, seed=2), progress=False)
    scan = raw.save(tmp_path / "ball.jsonl")
    calibrate = load_script("calibrate")
    out = tmp_path / "cal.yaml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        assert calibrate.main([str(scan), "--ball-radius", "30", "--tank", "t", "--output", str(out)]) == 0
    cal = load_calibration(out)
    for name in ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "step_scale"):
        low, high = cal.intervals[name]
        assert low <= getattr(true, name) <= high, name
    assert cal.geometry.cross_section_mm2 == pytest.approx(0.85 * 60000.0, rel=0.002)  # from the ball's volume
    assert "spin_zero_deg" in cal.not_estimated  # the ball's symmetry, never an optimiser's trial value


def test_the_profile_model_repairs_a_level_spike_once_not_per_trial(monkeypatch):
    from dipnet.calibration.model import ProfileModel, State
    from dipnet.preprocessing import preprocess as preprocess_module

    grid = Grid(16, 3, 80.0)
    raw = simulate_scan(Ball(RADIUS), fibonacci_hemisphere(6), tank=Tank(cross_section_mm2=AREA))
    clean = ProfileModel(raw, grid).measurement(State(RigGeometry()))
    spiked = simulate_scan(Ball(RADIUS), fibonacci_hemisphere(6), tank=Tank(cross_section_mm2=AREA))
    middle = len(spiked.orientations[2].values) // 2
    spiked.orientations[2].values[middle] += 5.0  # a 5 mm level spike in one reading
    with pytest.warns(UserWarning, match="repaired 1 outlier"):
        model = ProfileModel(spiked, grid)  # the spike is found once, when the model is made

    def no_repair(*args, **kwargs):
        raise AssertionError("readings repaired again in a trial")

    monkeypatch.setattr(preprocess_module, "repair_readings", no_repair)
    for offset in (0.0, 2.0):  # two trial geometries
        trial = model.measurement(State(RigGeometry(tilt_axis_offset_mm=offset)))
        assert trial.metadata["readings"] == model.readings.to_json()
    repaired = model.measurement(State(RigGeometry()))
    np.testing.assert_allclose(repaired.profiles, clean.profiles, atol=1e-4 * float(clean.profiles.max()))  # interpolated
