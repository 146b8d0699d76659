"""Measurement validation: consistent dips pass, impossible ones are refused, disagreeing ones named."""

import math
import re

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators.analytic import ball_profiles
from dipnet.preprocessing.validation import (MeasurementValidationError, reading_noise, reading_noise_leak,
                                            validate_measurement,
                                            working_ball_volume)

GRID = Grid(16, 3, 100.0)
EDGES = torch.linspace(-50, 50, 17, dtype=torch.float64)


def _ball(k=12, radius=20.0) -> np.ndarray:
    return ball_profiles(fibonacci_hemisphere(k), EDGES, torch.zeros(3), radius).numpy()


def _measurement(profiles, k=12) -> DipMeasurement:
    return DipMeasurement(fibonacci_hemisphere(k), profiles, 100.0 / 16, np.full(k, -50.0))


def test_the_working_ball_volume():
    assert working_ball_volume(GRID) == pytest.approx(4 / 3 * math.pi * GRID.radius**3)
    assert working_ball_volume(Grid(16, 2, 100.0)) == pytest.approx(math.pi * Grid(16, 2, 100.0).radius**2)


def test_consistent_dips_pass_without_warnings():
    report = validate_measurement(_measurement(_ball()), GRID)
    assert report.warnings == [] and report.metrics()["validation_warnings"] == 0
    assert report.stats["total_spread"] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("change,message", [
    (lambda p: p * 1e3, "working ball"),         # wrong units: a thousand times the ball
    (lambda p: p * 1e-6, "less than one voxel"),  # litres for mm^3: the audit's case, which passed with exit 0
    (lambda p: -p, "sums to"),
])
def test_impossible_dips_are_refused(change, message):
    with pytest.raises(MeasurementValidationError, match=message):
        validate_measurement(_measurement(change(_ball())), GRID)


def test_a_dip_measuring_less_is_named():
    profiles = _ball()
    profiles[3] *= 0.8  # a truncated dip
    with pytest.warns(UserWarning, match=r"dips \[3\]"):
        report = validate_measurement(_measurement(profiles), GRID)
    assert report.stats["totals_off"] == [3] and len(report.warnings) == 1


def test_a_mislabelled_direction_is_named_by_its_profile_not_its_total():
    """A ball 15 mm off the centre: every dip has the same total, so only the profiles tell directions apart.
    Dip 0 given dip 5's direction (37 deg away) pairs with dip 5 and measures another profile: named. The
    same dip recorded twice, once started a slab and a half lower (its profile on other heights), is not."""
    directions = fibonacci_hemisphere(12)
    centre = torch.tensor([15.0, 0.0, 0.0])
    profiles = ball_profiles(directions, EDGES, centre, 20.0).numpy()
    mislabelled = directions.clone()
    mislabelled[0] = directions[5]
    with pytest.warns(UserWarning, match=r"1 of 1 pair\(s\) of directions .* measure different profiles .* "
                      r"dips 0 and 5, whose volumes below a "
                      r"height differ by up to [\d.e+]+ mm\^3, [\d.]+% of [\d.e+]+ mm\^3\)"):
        report = validate_measurement(DipMeasurement(mislabelled, profiles, 100.0 / 16, np.full(12, -50.0)), GRID)
    assert report.stats["duplicate_max_discrepancy"] > 0.2
    h = 100.0 / 16
    lower = torch.linspace(-50 - 1.5 * h, 50 - 1.5 * h, 17, dtype=torch.float64)
    again = ball_profiles(directions[5:6], lower, centre, 20.0).numpy()
    repeated = DipMeasurement(torch.cat([directions, directions[5:6]]), np.concatenate([profiles, again]), h,
                              np.concatenate([np.full(12, -50.0), [-50.0 - 1.5 * h]]))
    report = validate_measurement(repeated, GRID)
    assert report.stats["duplicate_direction_pairs"] == 1 and report.warnings == []
    assert report.stats["duplicate_max_discrepancy"] < 0.02


def _readings(sigma: float, seed: int, n: int = 80) -> np.ndarray:
    """A dip's level readings (mm) at 1 mm steps: a smooth 30 mm rise plus white noise of ``sigma``."""
    rise = 30.0 * (1 - np.cos(np.pi * np.clip(np.arange(n) / (n - 1), 0, 1))) / 2
    return 150.0 + rise + np.random.default_rng(seed).normal(0.0, sigma, n)


@pytest.mark.parametrize("sigma", [0.01, 0.1])
def test_the_readings_noise_is_their_white_noise_and_the_stated_one_is_compared_to_it(sigma):
    dips = [_readings(sigma, seed) for seed in range(40)]
    found, ratio = reading_noise(dips, [sigma] * 40)
    assert found == pytest.approx(sigma, rel=0.1)
    assert ratio == pytest.approx(1.0, rel=0.1)
    _, overstated = reading_noise(dips, [5 * sigma] * 40)
    assert overstated == pytest.approx(5.0, rel=0.1)
    assert math.isnan(reading_noise(dips, [None] * 40)[1])  # nothing stated: nothing to compare


def test_the_leak_tells_white_noise_from_a_rise_the_estimate_takes_for_noise():
    """White noise has the same third-difference sigma at twice the step (ratio 1); a sharp rise read at a coarse
    step (the 30 mm rise over 20 readings) has third differences that grow with the step's cube, and the
    estimate holds it (a correct statement reads as a quarter of it): the ratio is far above 1."""
    assert reading_noise_leak([_readings(0.1, seed) for seed in range(40)]) == pytest.approx(1.0, abs=0.15)
    coarse = [_readings(1e-3, seed, n=20) for seed in range(40)]
    assert reading_noise(coarse, [1e-3] * 40)[1] < 0.3 and reading_noise_leak(coarse) > 4
    assert math.isnan(reading_noise_leak([np.arange(7.0)]))  # no dip of 8 readings


def test_rounded_noise_free_readings_show_the_rounding():
    quantum = 0.05
    dips = [np.round(_readings(0.0, 0) / quantum) * quantum, np.full(20, 150.0)]  # a rise, and a level that never moves
    found, ratio = reading_noise(dips, [0.0, 0.0], quantum)
    rounding = quantum / math.sqrt(12)
    assert found >= rounding and ratio == pytest.approx(rounding / found)
    assert ratio > 0.7
    assert math.isnan(reading_noise([np.arange(3.0)], [0.1])[0])  # no third difference


# ----------------------------------------------------------------------------- the object beyond the working ball
def _simulated(shape, grid: Grid, snr_db=None, k=12):
    """A simulated raw scan of ``shape`` (1 mm steps) and its measurement on ``grid``'s slabs."""
    from dipnet.simulator.physics import LevelSensor
    from dipnet.simulator.simulate import simulate_measurement

    return simulate_measurement(shape, fibonacci_hemisphere(k), grid=grid, step_mm=1.0, seed=3, progress=False,
                                sensor=LevelSensor(snr_db=snr_db))


def test_an_object_beyond_the_working_ball_is_refused_naming_the_extent_it_needs():
    """Before: a torus of radius 40 mm on a grid whose working ball has a radius of 36.9 mm (extent 82 mm at 20^3)
    passed validation, and the run was `consistent` (IoU 0.756 against 0.916 at 100 mm): the slabs still held 99.9 %
    of its volume, so the "beyond the slabs" check had nothing to say. Its readings show it reaches 39 mm."""
    from dipnet.shapes.builtin import builtin_shape

    torus = builtin_shape("torus", 3, 40.0)
    small = Grid(20, 3, 82.0)
    _, measured = _simulated(torus, small)
    with pytest.raises(MeasurementValidationError, match=r"reaches beyond the working ball of radius 36\.9 mm "
                                                         r"\(extent_mm=82 at resolution 20\).*increase extent_mm to "
                                                         r"(\d+) or more") as refused:
        validate_measurement(measured, small)
    needed = int(re.search(r"extent_mm to (\d+)", str(refused.value)).group(1))
    assert 95 <= needed <= 100  # puts the reach found (39-40 mm) at 90 % of the ball, whose radius grows past 40 mm
    validate_measurement(_simulated(torus, Grid(20, 3, needed))[1], Grid(20, 3, needed))
    # the same profiles without what the readings showed (a file written before reach_mm): their slabs tell it too
    slabs = DipMeasurement(measured.directions, measured.profiles, measured.slab_thickness, measured.offsets,
                           metadata={"reading_noise_volume": measured.metadata["reading_noise_volume"]})
    with pytest.raises(MeasurementValidationError, match="reaches beyond the working ball"):
        validate_measurement(slabs, small)


@pytest.mark.parametrize("name", ["ball", "torus", "chamber_box"])
@pytest.mark.parametrize("snr_db", [None, 20.0])
def test_an_object_just_inside_the_working_ball_passes(name, snr_db):
    """A shape as large as the working ball: neither the interpolation between readings (the last step's rise
    spread past the object's end) nor the noise makes it reach beyond (noise-free, at most 0.98 of the radius)."""
    from dipnet.shapes.builtin import builtin_shape

    grid = Grid(20, 3, 82.0)
    _, measured = _simulated(builtin_shape(name, 3, grid.radius), grid, snr_db, k=30)
    validate_measurement(measured, grid)
    reach = measured.reach()
    assert np.nanmax(np.fmax(-reach[:, 0], reach[:, 1])) < grid.radius


def test_a_re_binned_measurement_keeps_what_its_own_slabs_showed(tmp_path):
    """The chamber box's measurement (a 45 mm corner radius) read from a file onto a grid whose working ball has
    a radius of 36 mm: the slabs it was saved on show where the object reaches, before re-binning spreads it."""
    from dipnet.preprocessing.sources import read_recorded
    from dipnet.shapes.builtin import builtin_shape

    _, measured = _simulated(builtin_shape("chamber_box", 3, 45.0), Grid(20, 3, 111.2), k=30)
    bare = DipMeasurement(measured.directions, measured.profiles, measured.slab_thickness, measured.offsets,
                          metadata={"reading_noise_volume": measured.metadata["reading_noise_volume"]})
    path = bare.save(tmp_path / "measurement.npz")  # as a file written before reach_mm was recorded
    small = Grid(20, 3, 80.0)
    with pytest.raises(MeasurementValidationError, match=r"radius 36\.0 mm"):
        validate_measurement(read_recorded(str(path), small), small)
    validate_measurement(read_recorded(str(path), Grid(20, 3, 111.2)), Grid(20, 3, 111.2))


def test_the_bundled_recording_of_the_cats_is_not_refused():
    """The authors' cats as `experiment=cats_real` reads them: no dip reaches beyond the 360 mm grid's working
    ball at 40^3 (radius 171 mm; the complete dips reach 163 mm) nor at 24^3 (165 mm)."""
    from dipnet.preprocessing.datasets import CATS_CSV
    from dipnet.preprocessing.sources import read_recorded

    options = dict(cross_section_mm2=183600.0, geometry={"pivot_mm": 188.0, "tilt_axis_offset_mm": -18.0},
                   centre="extent", truncated="keep", tail_fraction=0.1, tail_tol=0.04, smooth=True)
    for n in (40, 24):
        grid = Grid(n, 3, 360.0)
        validate_measurement(read_recorded(str(CATS_CSV), grid, **options), grid)


#: A scan read with another rig's calibration file (same rig name and tank).
_OWN_RIG = {"pivot_mm": 100.0, "tilt_axis_offset_mm": -20.0, "tilt_zero_deg": 6.0}
_OTHER_RIG = {"pivot_mm": 12.0, "tilt_axis_offset_mm": 16.0, "tilt_zero_deg": 1.0}


def _scan_with_calibrations(tmp_path):
    """A 25 mm ball 10 mm off the spin axis dipped 24 times (30 dB) on the rig :data:`_OWN_RIG` (rig 'lab-rig',
    tank 'tank-1'), and two calibration files of that rig and tank: its own and :data:`_OTHER_RIG`'s."""
    from dipnet.core.calibration_file import Calibration, save_calibration
    from dipnet.core.geometry import RigGeometry
    from dipnet.shapes import Ball
    from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank, simulate_scan

    raw = simulate_scan(Ball(25.0, center=(10.0, 0.0, 0.0)), fibonacci_hemisphere(24), tank=Tank(60000.0),
                        geometry=RigGeometry(**_OWN_RIG), sensor=LevelSensor(snr_db=30.0, seed=1),
                        protocol=DipProtocol(extra_steps=8), progress=False)
    raw.header.rig, raw.header.config["tank_id"] = "lab-rig", "tank-1"
    files = [save_calibration(Calibration(RigGeometry(**values), "lab-rig", "tank-1", method="reference"),
                              tmp_path / name) for name, values in (("own.yaml", _OWN_RIG), ("other.yaml", _OTHER_RIG))]
    return raw.save(tmp_path / "scan.jsonl"), *files


def test_another_rigs_calibration_file_is_named_not_the_grid(tmp_path):
    """Before: the scan read with another rig's calibration file was refused by the reach check with "increase
    extent_mm to 381", which names the grid where the geometry is at fault (on a grid for the ball, 100 mm: "profile
    15 sums to 0 mm^3: a dip cannot displace a negative or zero volume"). Now the dips are tested for one placement
    of one object (their heights need a radius of 145 mm about any centre, no dip is wider than 46 mm) before their
    signs, and the refusal names the calibration file and what to do; the rig's own file passes. A geometry given
    as values is named the same way."""
    import warnings

    from dipnet.preprocessing import validation
    from dipnet.preprocessing.recorded import read_raw_recording

    scan, own, other = _scan_with_calibrations(tmp_path)
    for extent in (100.0, 200.0):
        grid = Grid(24, 3, extent)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the volume outside the slabs
            misplaced = read_raw_recording(scan, grid, calibration=other)
        with pytest.raises(MeasurementValidationError,
                           match=r"reaches beyond the working ball .* yet no dip shows it wider than \d+\.\d mm and "
                                 r"their heights place no one object .* comes from the calibration file .*other\.yaml "
                                 r"\(rig 'lab-rig', tank 'tank-1', reference, .*recalibrate this rig .*A larger "
                                 r"extent_mm \(\d+\) would only hold a misplaced object"):
            validate_measurement(misplaced, grid)
        placement = validation.dip_placement(misplaced)
        assert placement.implausible and placement.radius_mm > 2 * placement.width_mm
        right = read_raw_recording(scan, grid, calibration=own)
        validate_measurement(right, grid)
        fits = validation.dip_placement(right)
        assert fits.radius_mm == pytest.approx(0.5 * fits.width_mm, rel=0.05) and not fits.implausible
    grid = Grid(24, 3, 200.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        given = read_raw_recording(scan, grid, geometry=_OTHER_RIG)
    with pytest.raises(MeasurementValidationError, match=r"the geometry given \(pivot_mm=12, tilt_axis_offset_mm=16, "
                                                         r"tilt_zero_deg=1\) is likely wrong: check the values"):
        validate_measurement(given, grid)


def test_an_object_beyond_the_grid_read_with_a_calibration_file_names_both(tmp_path):
    """The rig's own file on a grid too small for the ball (which is 35 mm from the centre): the dips place one
    object, so the grid is at fault (extent_mm named) and the file is named as the other possibility."""
    from dipnet.preprocessing.recorded import read_raw_recording

    scan, own, _ = _scan_with_calibrations(tmp_path)
    grid = Grid(24, 3, 60.0)
    with pytest.warns(UserWarning, match="outside the slabs"):
        measurement = read_raw_recording(scan, grid, calibration=own)
    with pytest.raises(MeasurementValidationError, match=r"increase extent_mm to \d+ or more .* comes from the "
                                                         r"calibration file .*own\.yaml .*: if the object is not that "
                                                         r"far off the spin axis \(no dip shows it wider than"):
        validate_measurement(measurement, grid)


def test_dips_that_trap_air_in_a_cavity_are_named_by_their_totals():
    """The chamber box dipped with its channel's mouth pointing down keeps its chamber's air (the simulator's
    pockets): those dips measure the box and the chamber, 14 % more than the dips that let the air out, and the
    warning names the trapped air among the causes."""
    from dipnet.shapes.builtin import builtin_shape
    from dipnet.simulator.pockets import Pockets
    from dipnet.simulator.simulate import simulate_measurement

    grid = Grid(24, 3, 110.0)
    directions = np.concatenate([fibonacci_hemisphere(8).numpy(), -fibonacci_hemisphere(4).numpy()])
    _, measurement = simulate_measurement(builtin_shape("chamber_box", 3, 45.0), directions, grid=grid,
                                          pockets=Pockets(32), progress=False)
    with pytest.warns(UserWarning, match="air trapped in a cavity that opens downward"):
        report = validate_measurement(measurement, grid)
    low = np.flatnonzero(directions[:, 2] < -0.5)
    assert set(low) <= set(report.stats["totals_off"]) and report.stats["total_spread"] > 0.1
    assert any("air trapped in a cavity that opens downward" in w for w in report.warnings)


def test_a_grid_that_is_no_grid_is_named():
    """Before: validate_measurement(measurement, 16) failed with
    "AttributeError: 'int' object has no attribute 'ndim'"."""
    with pytest.raises(TypeError, match=r"grid must be a dipnet.Grid, e.g. Grid\(16, "):
        validate_measurement(_measurement(_ball()), 16)


def _disk_2d(k: int = 8) -> DipMeasurement:
    """A 2D measurement: a disk of radius 20 mm at the centre on a 16^2 grid of 100 mm, slabs in mm^2."""
    from dipnet.core.orientations import angles_2d, directions_2d
    from dipnet.shapes.analytic import Disk

    directions = directions_2d(angles_2d(k))
    profiles = torch.diff(Disk(20.0).volume_below(directions, EDGES), dim=1)
    return DipMeasurement(directions, profiles, 100.0 / 16, np.full(k, -50.0))


@pytest.mark.parametrize("change,message", [
    (lambda p: p * 1e3, r"holds [\d.e+]+ mm\^2, more than the working ball's [\d.e+]+ mm\^2"),
    (lambda p: p * 1e-6, r"less than one voxel's [\d.]+ mm\^2 .*cm\^2 or m\^2 for mm\^2"),
    (lambda p: -p, r"sums to -[\d.e+]+ mm\^2"),
])
def test_2d_refusals_name_areas_not_volumes(change, message):
    """2D slabs are areas: a refusal of a 2D measurement says mm^2 (and the unit slips of areas), never mm^3."""
    m = _disk_2d()
    bad = DipMeasurement(m.directions, change(m.profiles), m.slab_thickness, m.offsets)
    with pytest.raises(MeasurementValidationError, match=message) as info:
        validate_measurement(bad, Grid(16, 2, 100.0))
    assert "mm^3" not in str(info.value)


def test_2d_warnings_name_areas_not_volumes():
    m = _disk_2d()
    profiles = m.profiles.clone()
    profiles[3] *= 0.8  # a truncated dip
    with pytest.warns(UserWarning, match=r"median [\d.]+ mm\^2"):
        report = validate_measurement(DipMeasurement(m.directions, profiles, m.slab_thickness, m.offsets),
                                      Grid(16, 2, 100.0))
    assert not any("mm^3" in w for w in report.warnings)


def test_directions_all_pointing_down_are_named():
    """A file recording each dip's direction of motion (down) instead of the object's up: the dips of a ball 15 mm
    off the centre along the reversed directions are exactly those of the ball mirrored through the centre along
    the true ones, so only the directions' half tells. All down: a warning; some down (a rig tilting past 90
    deg): none. In 2D the horizontal direction of the equal angles is either way."""
    centre = torch.tensor([15.0, 0.0, 5.0], dtype=torch.float64)
    up = fibonacci_hemisphere(12)
    down = ball_profiles(-up, EDGES, centre, 20.0)
    assert torch.allclose(down, ball_profiles(up, EDGES, -centre, 20.0))  # the point-reflected object's dips
    with pytest.warns(UserWarning, match=r"points down \(z < 0 in 12 of 12, none above 0\).*negate them"):
        report = validate_measurement(DipMeasurement(-up, down, 100.0 / 16, np.full(12, -50.0)), GRID)
    assert report.stats["directions_down"] == 12
    mixed = up.clone()
    mixed[:3] = -mixed[:3]
    report = validate_measurement(DipMeasurement(mixed, ball_profiles(mixed, EDGES, centre, 20.0), 100.0 / 16,
                                                 np.full(12, -50.0)), GRID)
    assert report.warnings == [] and report.stats["directions_down"] == 3
    m = _disk_2d()
    with pytest.warns(UserWarning, match=r"every direction points down \(y < 0 in 7 of 8"):  # one horizontal
        validate_measurement(DipMeasurement(-m.directions, m.profiles.flip(1), m.slab_thickness, m.offsets),
                             Grid(16, 2, 100.0))


def test_a_measurement_of_the_other_dimension_names_the_ndim_to_set():
    """Before: "m.npz: 2D directions for a 3D grid", naming no option (a raw scan's says "set ndim=2")."""
    m = DipMeasurement(torch.tensor([[1.0, 0.0], [0.0, 1.0]]), torch.ones(2, 8), 1.0, torch.full((2,), -4.0),
                       metadata={"path": "m.npz"})
    with pytest.raises(MeasurementValidationError, match=r"m.npz: 2D directions for a 3D grid: set ndim=2$"):
        validate_measurement(m, Grid(16, extent=80.0))
