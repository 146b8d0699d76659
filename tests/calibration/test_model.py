"""The calibration's forward model and geometry fit (dipnet.calibration.model): the measurement a trial
geometry makes of a scan, the least-squares geometry step, identifiability against the object's own gauges,
the report and the calibration file's record of it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.calibration.model import (
    NOT_ESTIMATED,
    CalibrationError,
    CalibrationReport,
    ProfileModel,
    State,
    fit_geometry,
    identifiability,
    self_section_bias,
    to_calibration,
)
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.shapes import Ball, Box
from dipnet.simulator.physics import DipProtocol, Tank, simulate_scan

from calibration_helpers import AREA, RADIUS

TRUE = RigGeometry(pivot_mm=10.0)


@pytest.fixture(scope="module")
def box_scan():
    """12 noise-free dips of an off-centre box on a rig whose pivot is 10 mm; the model on a 24^3 grid and
    the box's occupancy there."""
    shape = Box((20.0, 12.0, 16.0), (4.0, -3.0, 2.0))
    raw = simulate_scan(shape, fibonacci_hemisphere(12), tank=Tank(60000.0), geometry=TRUE,
                        protocol=DipProtocol(step_mm=1.0), progress=False)
    grid = Grid(24, extent=100.0)
    return ProfileModel(raw, grid), shape.occupancy(grid, supersample=2).double()


def _centroids(m) -> torch.Tensor:
    mids = m.offsets[:, None] + m.slab_thickness * (torch.arange(m.n_slabs) + 0.5)
    return (m.profiles * mids).sum(1) / m.profiles.sum(1)


def test_a_start_height_offset_moves_every_dip_by_that_much(box_scan):
    model, _ = box_scan
    base = model.measurement(State(TRUE))
    moved = model.measurement(State(TRUE, t0_mm=2.0))
    torch.testing.assert_close(_centroids(moved) - _centroids(base), torch.full((12,), 2.0, dtype=torch.float64),
                               atol=0.01, rtol=0.0)  # measured 1.991 - 2.001 mm
    torch.testing.assert_close(moved.profiles.sum(1), base.profiles.sum(1))  # the same volumes


def test_the_true_geometry_explains_the_profiles_and_the_fit_finds_it(box_scan):
    """At the true pivot the residual is the voxelisation's only (20x smaller than at pivot 0: measured 44 vs 949
    mm^3 RMS); the geometry step from the ideal rig comes back to 10 mm (measured 10.01)."""
    model, occupancy = box_scan
    at_truth = np.sqrt(np.mean(model.residual(State(TRUE), occupancy, 1.0) ** 2))
    at_zero = np.sqrt(np.mean(model.residual(State(RigGeometry()), occupancy, 1.0) ** 2))
    assert at_truth < at_zero / 10
    state, sigma = fit_geometry(model, occupancy, State(RigGeometry()), ("pivot_mm",))
    assert state.geometry.pivot_mm == pytest.approx(10.0, abs=0.1)
    assert sigma == pytest.approx(at_zero)  # the noise scale defaults to the starting residual


def test_the_spin_zero_trades_with_the_objects_own_rotation(box_scan):
    """Turning the whole rig about the spin axis is turning the unknown object: with the gauges the spin zero is
    named undetermined (with its partner), the pivot is not."""
    model, occupancy = box_scan
    report = identifiability(model, occupancy, State(TRUE), ("pivot_mm", "spin_zero_deg"))
    assert report.standard_errors["pivot_mm"] < 0.1
    assert set(report.undetermined) == {"spin_zero_deg"} and "rot_z_deg" in report.undetermined["spin_zero_deg"]


@pytest.mark.parametrize("params", [(), ("pivot_mm", "wobble_mm")])
def test_unknown_or_no_parameters_are_named(box_scan, params):
    model, occupancy = box_scan
    with pytest.raises(CalibrationError, match="unknown or no calibration parameter"):
        fit_geometry(model, occupancy, State(TRUE), params)


def test_a_parameter_given_twice_is_named(box_scan):
    """``calibrate.py --params ... pivot_mm`` (or ``calibration.params``) with a repeat: a numpy ``setting an array
    element with a sequence`` error, or a fit that passed unsaid."""
    model, occupancy = box_scan
    with pytest.raises(CalibrationError, match=r"calibration parameter\(s\) pivot_mm given more than once"):
        fit_geometry(model, occupancy, State(TRUE), ("pivot_mm", "tilt_zero_deg", "pivot_mm"))


def test_the_self_section_bias_grows_with_the_partial_volume_and_is_capped():
    assert self_section_bias(0.0) == 0.0
    assert self_section_bias(0.1) == pytest.approx(0.0095)
    assert self_section_bias(0.3) == pytest.approx(0.0855) and self_section_bias(0.6) == 0.11


def _report() -> CalibrationReport:
    return CalibrationReport(estimates={"pivot_mm": 20.2, "tilt_zero_deg": 0.0},
                             standard_errors={"pivot_mm": 0.1, "tilt_zero_deg": 3.0},
                             correlations={"pivot_mm": {"tilt_zero_deg": 0.2}},
                             undetermined={"tilt_zero_deg": "a centred ball's symmetry"},
                             intervals={"pivot_mm": (20.0, 20.4)}, method="reference")


def test_the_report_says_what_is_determined():
    report = _report()
    assert report.determined == ["pivot_mm"]
    table = report.table().splitlines()
    assert table[0].split()[:2] == ["parameter", "estimate"]
    assert table[1].split()[:4] == ["pivot_mm", "20.2", "[20,", "20.4]"] and table[1].endswith("yes")
    assert "no, kept at the configured value: a centred ball's symmetry" in table[2]
    assert table[3].startswith("sensor_lag_s")
    assert table[-1].startswith("turning sense") and "mirrors every shape" in table[-1]
    record = report.to_dict()
    assert record["intervals_90"] == {"pivot_mm": [20.0, 20.4]} and record["not_estimated"] == NOT_ESTIMATED
    assert record["method"] == "reference" and np.isnan(record["residual_rms"])


def test_the_calibration_file_never_labels_a_kept_value_an_estimate():
    cal = to_calibration(RigGeometry(pivot_mm=20.2), _report(), "fake-grbl", "tank-1", notes="test")
    assert (cal.rig, cal.tank, cal.method, cal.notes) == ("fake-grbl", "tank-1", "reference", "test")
    assert cal.intervals == {"pivot_mm": (20.0, 20.4)} and cal.uncertainty == {"pivot_mm": 0.1}
    assert cal.not_estimated["tilt_zero_deg"].startswith("not determined by the dips, configured value kept")
    assert cal.not_estimated["sensor_lag_s"] == NOT_ESTIMATED["sensor_lag_s"]
    assert "not among the calibrated parameters" in cal.not_estimated["tilt_axis_offset_mm"]
    assert "pivot_mm" not in cal.not_estimated and "cross_section_mm2" not in cal.not_estimated  # None: no field


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
    # interpolated
    np.testing.assert_allclose(repaired.profiles, clean.profiles, atol=1e-4 * float(clean.profiles.max()))


def test_a_coarse_stage_step_is_warned_about_once_not_per_trial_geometry(caplog):
    """A stage step thicker than a slab is warned about when the model is made; the trial geometries' preprocessing
    and the noise residual's copy of the scan (the same stage) do not say it again (calibrate.py said it four
    times)."""
    import logging
    import warnings

    from dipnet.calibration.model import State
    from dipnet.calibration.reference import noise_residual

    grid = Grid(16, 3, 80.0)  # 5 mm slabs
    raw = simulate_scan(Ball(RADIUS), fibonacci_hemisphere(6), tank=Tank(cross_section_mm2=AREA),
                        protocol=DipProtocol(step_mm=8.0), progress=False)
    with warnings.catch_warnings(record=True) as caught, caplog.at_level(logging.WARNING):
        warnings.simplefilter("always")
        model = ProfileModel(raw, grid)
        for offset in (0.0, 2.0, 4.0):  # three trial geometries
            model.measurement(State(RigGeometry(tilt_axis_offset_mm=offset)))
        noise_residual(model, State(RigGeometry()))
    said = [str(w.message) for w in caught if "the stage step" in str(w.message)]
    logged = [r.getMessage() for r in caplog.records if "the stage step" in r.getMessage()]
    assert len(said) == 1 and len(logged) == 1, (said, logged)
    assert said[0].startswith("the stage step (8 mm) is 1.6 slabs thick (slab 5 mm)")
