"""The dipping physics: Archimedes' fixed point, sensors (noise, SNR, quantisation, drift), balance."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.orientations import directions_2d, fibonacci_hemisphere
from dipnet.simulator.physics import Balance, DipProtocol, LevelSensor, Tank, simulate_scan, solve_dip
from dipnet.shapes import Ball, Disk, load_mesh

BALL = Ball(40.0, center=(3.0, -2.0, 1.0))
DIRS = fibonacci_hemisphere(6)
EXACT = LevelSensor(quantum_mm=0.0)


def _exact_volume(shape, direction, heights) -> np.ndarray:
    return shape.volume_below(torch.as_tensor(direction).reshape(1, -1), torch.as_tensor(heights))[0].numpy()


@pytest.mark.parametrize("shape, dirs, area", [(BALL, DIRS, 60000.0),
                                               (Disk(40.0, (2.0, 1.0)), directions_2d([0, 50, 120]), 300.0)])
def test_levels_satisfy_archimedes_fixed_point(shape, dirs, area):
    tank = Tank(cross_section_mm2=area, rest_level_mm=150.0)
    scan = simulate_scan(shape, dirs, tank=tank, sensor=EXACT, progress=False)
    t_start = scan.header.t_start_mm
    assert t_start == pytest.approx(-(shape.radius() + DipProtocol().clearance_mm))
    for o in scan.orientations:
        rise = o.values - tank.rest_level_mm
        volume = _exact_volume(shape, o.unit_direction, t_start + o.stage_mm + rise)
        np.testing.assert_allclose(area * rise, volume, rtol=0, atol=1e-9 * shape.volume)
        assert rise[0] == 0.0 and np.all(np.diff(rise) >= 0)
        assert rise[-1] == pytest.approx(shape.volume / area, rel=1e-12)  # fully under water at the end
        assert o.meta["residual_mm3"] < 1e-9 * shape.volume
        # the submerged depth grows by d + (delta_{i+1} - delta_i) per step
        depth = o.stage_mm + rise
        np.testing.assert_allclose(np.diff(depth), 1.0 + np.diff(rise))


def test_rise_exceeds_the_naive_one_by_the_displacement_feedback():
    """Without the feedback the rise would be V(t_start + s) / A: the true one is larger."""
    tank = Tank()
    stage = np.arange(60.0)
    state = solve_dip(BALL, DIRS[0].numpy(), tank, stage, -45.0)
    naive = _exact_volume(BALL, DIRS[0].numpy(), -45.0 + stage) / tank.cross_section_mm2
    partial = (naive > 0) & (naive < BALL.volume / tank.cross_section_mm2)
    assert np.all(state.rise_mm[partial] > naive[partial])


def test_object_wider_than_tank_is_refused():
    with pytest.raises(ValueError, match="cannot be dipped"):
        simulate_scan(BALL, DIRS, tank=Tank(cross_section_mm2=4000.0), sensor=EXACT, progress=False)


@pytest.mark.parametrize("bad,message", [([0.0, 0.0, 0.0], r"a zero vector in rows \[1\]"),
                                         ([float("nan"), 0.0, 1.0],
                                          r"non-finite \(NaN or inf\) components in rows \[1\]")])
def test_a_zero_or_nan_direction_is_named(bad, message):
    """Before: 'ValueError: cannot convert float NaN to integer' from deep in the dip solver (the operator named
    such rows already); a direction of any other length is normalised, as the operator does."""
    with pytest.raises(ValueError, match=message):
        simulate_scan(BALL, torch.tensor([[0.0, 0.0, 1.0], bad]), sensor=EXACT, progress=False)
    unit, longer = (simulate_scan(BALL, d, sensor=EXACT, progress=False) for d in (DIRS[:2], 3 * DIRS[:2]))
    np.testing.assert_allclose(longer.orientations[1].values, unit.orientations[1].values)


def test_timing_and_schedule():
    protocol = DipProtocol(step_mm=2.0, clearance_mm=4.0, extra_steps=2, settle_s=3.0, reorient_s=20.0)
    scan = simulate_scan(BALL, DIRS[:2], sensor=EXACT, protocol=protocol, progress=False)
    a, b = scan.orientations
    n = protocol.n_readings(BALL.radius())
    assert a.n_readings == n and np.all(np.diff(a.stage_mm) == 2.0)
    np.testing.assert_allclose(np.diff(a.time_s), 3.0)
    assert b.time_s[0] - a.time_s[-1] == pytest.approx(20.0 + 3.0)
    assert np.all(a.values[-protocol.extra_steps - 1:] == a.values[-1])  # extra readings under water
    assert a.values[1] == a.values[0]  # the clearance gives flat readings first


@pytest.mark.parametrize("option,message", [
    ({"clearance_mm": float("nan")}, r"protocol clearance_mm must be a finite number >= 0 \(mm\), got nan"),
    ({"settle_s": float("nan")}, r"protocol settle_s must be a finite number >= 0 \(s\), got nan"),
    ({"reorient_s": float("inf")}, r"protocol reorient_s must be a finite number >= 0 \(s\), got inf"),
    ({"clearance_mm": float("inf")}, r"protocol clearance_mm .* got inf"),
    ({"step_mm": float("inf")}, r"step_mm must be a finite, positive number \(mm\), got inf"),
    ({"extra_steps": 2.5}, r"extra_steps must be a whole number of readings >= 0, got 2.5"),
    ({"step_mm": True}, r"step_mm must be a finite, positive number \(mm\), got True"),  # was a 1 mm step, unsaid
    # text and null were compared, a TypeError naming no option ("'<=' not supported between 'int' and 'str'"),
    # or parsed: extra_steps='abc' gave "invalid literal for int() with base 10: 'abc'"
    ({"clearance_mm": "abc"}, r"protocol clearance_mm must be a finite number >= 0 \(mm\), got 'abc'"),
    ({"clearance_mm": None}, r"protocol clearance_mm must be a finite number >= 0 \(mm\), got None"),
    ({"step_mm": "1"}, r"step_mm must be a finite, positive number \(mm\), got '1'"),
    ({"extra_steps": "abc"}, r"extra_steps must be a whole number of readings >= 0, got 'abc'"),
    ({"extra_steps": "3"}, r"extra_steps must be a whole number of readings >= 0, got '3'"),
    ({"extra_steps": None}, r"extra_steps must be a whole number of readings >= 0, got None"),
    ({"extra_steps": float("inf")}, r"extra_steps must be a whole number of readings >= 0, got inf"),
])
def test_a_protocol_value_that_is_not_finite_is_named(option, message):
    """Before: DipProtocol(clearance_mm=nan) was accepted and the simulation failed with "cannot convert float NaN
    to integer" (reconstruct.py source.simulator.protocol.clearance_mm=nan: that line, exit 2), settle_s=nan or
    reorient_s=inf with "`x` must contain only finite values.", clearance_mm=inf with an OverflowError."""
    with pytest.raises(ValueError, match=message):
        DipProtocol(**option)
    assert DipProtocol(extra_steps=2.0).extra_steps == 2 and type(DipProtocol(extra_steps=2.0).extra_steps) is int


def test_snr_sets_the_stated_noise_level():
    snr_db = 20.0
    noisy = simulate_scan(BALL, DIRS, sensor=LevelSensor(snr_db=snr_db, quantum_mm=0.0), seed=3, progress=False)
    clean = simulate_scan(BALL, DIRS, sensor=EXACT, progress=False)
    residuals, sigmas = [], []
    for o, c in zip(noisy.orientations, clean.orientations):
        rises = np.diff(c.values)
        rises = rises[rises > 1e-12]
        expected = np.sqrt(np.mean(rises**2)) / 10 ** (snr_db / 20)
        assert o.meta["noise_sigma"] == pytest.approx(expected, rel=1e-6)
        residuals.append(o.values - c.values)
        sigmas.append(expected)
    r = np.concatenate(residuals)
    assert abs(r.mean()) < 0.2 * np.mean(sigmas)
    assert np.std(r) == pytest.approx(np.sqrt(np.mean(np.square(sigmas))), rel=0.1)


def test_fixed_sigma_quantisation_drift_and_seeds():
    clean = simulate_scan(BALL, DIRS, sensor=EXACT, progress=False)
    q = simulate_scan(BALL, DIRS[:3], sensor=LevelSensor(quantum_mm=0.04), progress=False)
    for o, c in zip(q.orientations, clean.orientations):
        steps = o.values / 0.04
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
        assert np.abs(o.values - c.values).max() <= 0.02 + 1e-12
    drift = simulate_scan(BALL, DIRS[:3], sensor=LevelSensor(quantum_mm=0.0, drift_mm_per_s=1e-3), progress=False)
    for o, c in zip(drift.orientations, clean.orientations):
        np.testing.assert_allclose(o.values - c.values, 1e-3 * o.time_s, atol=1e-12)
    sensor = LevelSensor(sigma_mm=0.05, quantum_mm=0.0)
    a = simulate_scan(BALL, DIRS, sensor=sensor, seed=1, progress=False)
    b = simulate_scan(BALL, DIRS, sensor=sensor, seed=1, progress=False)
    c = simulate_scan(BALL, DIRS, sensor=sensor, seed=2, progress=False)
    noise = np.concatenate([o.values - x.values for o, x in zip(a.orientations, clean.orientations)])
    assert np.std(noise) == pytest.approx(0.05, rel=0.1)
    assert all(np.array_equal(x.values, y.values) for x, y in zip(a.orientations, b.orientations))
    assert not np.array_equal(a.orientations[0].values, c.orientations[0].values)


def test_balance_reads_displaced_mass():
    scan = simulate_scan(BALL, DIRS[:2], sensor=Balance(quantum_g=0.0), progress=False)
    assert scan.header.quantity == "mass_g" and scan.header.units["value"] == "g"
    area = scan.header.tank_cross_section_mm2
    for o in scan.orientations:
        volume = o.values / 1e-3
        t = scan.header.t_start_mm + o.stage_mm + volume / area
        np.testing.assert_allclose(volume, _exact_volume(BALL, o.unit_direction, t), atol=1e-9 * BALL.volume)
        assert o.values[-1] == pytest.approx(1e-3 * BALL.volume)


@pytest.mark.parametrize("sensor, message", [
    (dict(sigma_mm=-0.5), r"sensor sigma_mm must be a number >= 0 \(0: none\), got -0.5"),
    (dict(quantum_mm=-0.04), r"sensor quantum_mm must be a number >= 0 \(0: none\), got -0.04"),
    (dict(sigma_mm=float("inf")), "sensor sigma_mm must be a number >= 0"),
    (dict(drift_mm_per_s=float("nan")), "sensor drift_mm_per_s must be a finite number"),
    (dict(snr_db=1e308), r"snr_db must be a number of dB in \[-20, 200\] or null"),
])
def test_negative_or_non_finite_noise_is_refused(sensor, message):
    with pytest.raises(ValueError, match=message):
        LevelSensor(**sensor)


def test_a_noise_sigma_beside_an_snr_is_refused():
    """The SNR sets the noise: before, ``sigma_mm=0.1`` with ``snr_db=30`` simulated a noise of 0.0009-0.0012 mm
    (the 30 dB one, 90x below the sigma asked for) without a word."""
    with pytest.raises(ValueError, match=r"the sensor's sigma_mm=0.1 mm and snr_db=30 both set its noise, and with "
                                         r"snr_db the sigma is ignored: give one "
                                         r"\(snr_db=null for a noise of 0.1 mm\)"):
        LevelSensor(sigma_mm=0.1, snr_db=30.0)
    with pytest.raises(ValueError, match=r"sigma_g=0.5 g and snr_db=20"):
        Balance(sigma_g=0.5, snr_db=20.0)
    assert LevelSensor(sigma_mm=0.0, snr_db=30.0).snr_db == 30.0 and LevelSensor(sigma_mm=0.1).sigma_mm == 0.1


def test_balance_checks_its_own_units():
    with pytest.raises(ValueError, match="sensor quantum_g must be a number >= 0"):
        Balance(quantum_g=-0.01)


@pytest.mark.parametrize("density", [True, "1e-3", 0.0, float("nan")])
def test_a_balance_density_that_is_not_a_positive_number_is_named(density):
    """Before: ``density_g_per_mm3=true`` was read as 1 g/mm^3 (a thousand times water's), exit 0; text failed when
    the readings were made, NaN and 0 only when the scan's header was written."""
    with pytest.raises(ValueError, match=r"sensor density_g_per_mm3 must be a finite, positive number \(g/mm\^3; "
                                         r"water 1e-3\), got " + re.escape(repr(density))):
        Balance(density_g_per_mm3=density)
    assert Balance(density_g_per_mm3=1).density_g_per_mm3 == 1


def test_a_tank_without_its_class_is_named():
    with pytest.raises(ValueError, match=r"the simulator's tank must be a Tank, got dict .*_target_: "
                                         r"dipnet.simulator.physics.Tank"):
        simulate_scan(BALL, DIRS, tank={"cross_section_mm2": 100.0}, progress=False)


@pytest.mark.parametrize("area", [True, "abc", float("nan"), -5.0])
def test_a_tank_section_that_is_not_a_positive_number_is_named(area):
    """Before: ``cross_section_mm2=true`` was read as a 1 mm^2 tank (refused later as one smaller than the object,
    "the tank's free cross-section (1)"), and a string failed in numpy's isfinite, naming no option."""
    message = r"tank cross_section_mm2 must be a finite, positive number \(mm\^2; mm in 2D\), got "
    with pytest.raises(ValueError, match=message + re.escape(repr(area))):
        Tank(cross_section_mm2=area)
    assert Tank(cross_section_mm2=np.float64(4000.0)).cross_section_mm2 == 4000.0


@pytest.mark.parametrize("level", [float("nan"), float("inf")])
def test_a_rest_level_that_is_not_finite_is_named(level):
    """Before: Tank(rest_level_mm=nan) was accepted and the simulation failed with "`x` must contain only finite
    values."; any finite level (0, negative) only offsets the readings."""
    with pytest.raises(ValueError, match=rf"tank rest_level_mm must be a finite level \(mm\), got {level}"):
        Tank(rest_level_mm=level)
    low = simulate_scan(BALL, DIRS[:1], tank=Tank(rest_level_mm=-100.0), sensor=EXACT, progress=False)
    base = simulate_scan(BALL, DIRS[:1], sensor=EXACT, progress=False)
    np.testing.assert_allclose(low.orientations[0].values + 250.0, base.orientations[0].values)


def test_a_quantum_as_large_as_the_whole_rise_is_refused():
    """The 40 mm ball (268,083 mm^3) raises the default tank's level by a few mm: a 5 mm quantum would round
    every reading of a dip to one or two levels (the audit's 'profile 0 sums to 0'); it is refused, naming
    the rise. A quantum of a tenth of the rise is only coarse."""
    rise = float(np.ptp(LevelSensor().ideal(Tank(), np.array([0.0, BALL.volume]))))
    assert 1.0 < rise < 10.0
    with pytest.raises(ValueError,
                       match=rf"quantum \({2 * rise:g} mm\) is at least the whole change .* \({rise:.3g} mm"):
        simulate_scan(BALL, DIRS[:2], sensor=LevelSensor(quantum_mm=2 * rise), progress=False)
    coarse = simulate_scan(BALL, DIRS[:2], sensor=LevelSensor(quantum_mm=0.1 * rise), progress=False)
    assert np.ptp(coarse.orientations[0].values) > 0.5 * rise


def test_a_balance_quantum_as_large_as_the_displaced_mass_is_refused_naming_the_mass():
    """A balance reads the displaced water's mass (268 g for the 40 mm ball), which no tank section divides: its
    refusal says so, and the remedy is not a smaller tank (the level sensor's)."""
    mass = BALL.volume * 1e-3
    with pytest.raises(ValueError, match=rf"\({mass:.3g} g, the mass of water it displaces\).*or dip a larger object"):
        simulate_scan(BALL, DIRS[:2], sensor=Balance(quantum_g=2 * mass), progress=False)


def test_mesh_wider_than_tank_is_refused_naming_file_and_option(tmp_path):
    path = tmp_path / "huge.stl"
    trimesh.creation.box(extents=(400.0, 400.0, 400.0)).export(str(path))
    with pytest.raises(ValueError, match=r"(?s)huge\.stl.*cannot be dipped.*shape\.scale="):
        simulate_scan(load_mesh(path), DIRS, sensor=EXACT, progress=False)
