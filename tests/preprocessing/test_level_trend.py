"""A falling level's trace in the readings: the tail slope of a dip and the dips' summary."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize

from dipnet.preprocessing.level_trend import level_fall, reading_noise, tail_slope


def _dip(fall_per_reading: float = 0.0, sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """Volumes of one dip's 80 readings: 10 before the object touches the water, a rise of 1000 over 40
    readings, 30 with the object under; a level falling ``fall_per_reading`` per reading all along."""
    rise = np.concatenate([np.zeros(10), np.linspace(0.0, 1000.0, 41)[1:], np.full(30, 1000.0)])
    noise = np.random.default_rng(seed).normal(0.0, sigma, rise.size)
    return rise - fall_per_reading * np.arange(rise.size) + noise


def _slope(volume: np.ndarray) -> float:
    return tail_slope(volume, scipy.optimize.isotonic_regression(volume).x)


def test_a_level_falling_after_the_object_is_under_has_its_slope():
    """Noise-free, the slope of the readings after the monotone fit reached its end is about the fall's (the
    fit's last plateau pools a few readings of the rise too), and 0 without one; the fit itself hides the
    fall (it ends flat)."""
    assert _slope(_dip()) == pytest.approx(0.0, abs=1e-9)
    falling = _dip(2.0)
    assert _slope(falling) == pytest.approx(-2.0, rel=0.1)
    fitted = scipy.optimize.isotonic_regression(falling).x
    assert np.all(np.diff(fitted) >= 0)


def test_a_dip_that_ends_before_the_object_is_under_has_no_slope():
    still_rising = _dip()[:50]
    assert math.isnan(_slope(still_rising))
    assert math.isnan(tail_slope(np.zeros(0), np.zeros(0)))
    with pytest.raises(ValueError, match="one shape"):
        tail_slope(np.zeros(5), np.zeros(4))


def test_the_reading_noise_is_estimated_from_second_differences():
    noisy = _dip(sigma=5.0, seed=1)
    assert reading_noise(noisy) == pytest.approx(5.0, rel=0.25)
    assert reading_noise(_dip()) == pytest.approx(0.0, abs=1e-9)
    assert reading_noise(np.ones(2)) == 0.0


def test_noise_alone_never_looks_like_a_falling_level():
    """Over 40 dips of white noise (sigma 1% of the volume) the tail slopes scatter about 0 or below (the
    tail starts 3 noise sigmas under the fit's end, where the rise still counts), so the share of a fall is
    not positive; a fall of 1 per reading (8% of the volume over a dip) is found many standard errors out."""
    volume = 1000.0
    still = np.array([_slope(_dip(sigma=10.0, seed=s)) for s in range(40)])
    share, sigmas = level_fall(still, np.full(40, 80), volume)
    assert share < 0.01 and sigmas < 3
    falling = np.array([_slope(_dip(1.0, sigma=10.0, seed=s)) for s in range(40)])
    share, sigmas = level_fall(falling, np.full(40, 80), volume)
    assert share == pytest.approx(0.08, abs=0.02) and sigmas > 10


def test_the_summary_of_agreeing_slopes_and_too_few():
    share, sigmas = level_fall(np.full(5, -2.0), np.full(5, 100), 1000.0)
    assert share == pytest.approx(0.2) and sigmas == math.inf
    assert level_fall(np.zeros(5), np.full(5, 100), 1000.0) == (0.0, 0.0)
    share, sigmas = level_fall(np.array([-1.0, np.nan, np.nan, -1.0]), np.full(4, 10), 100.0)
    assert math.isnan(share) and math.isnan(sigmas)


def test_a_fall_that_lasts_is_found_with_its_size_and_place():
    """A fall of 300 after reading 30 that lasts (a cavity flooding) is found at its size (within the rise between
    the two medians) and place; the same dip without it, one glitch of 300, and noise alone show none."""
    from dipnet.preprocessing.level_trend import level_drop

    flooding = _dip()
    flooding[31:] -= 300.0
    drop, at = level_drop(flooding)
    assert drop == pytest.approx(300.0, abs=3 * 25.0) and at == 30
    glitch = _dip()
    glitch[31] -= 300.0
    assert level_drop(_dip()) == level_drop(glitch) == (0.0, -1)
    rounded = 150.0 + _dip() / 6e4  # levels in mm, noise-free
    rounded[60:] -= 3e-14  # a last-bit difference of the simulator's fixed point, not a fall
    assert level_drop(rounded) == (0.0, -1)
    for seed in range(5):
        assert level_drop(_dip(sigma=5.0, seed=seed), sigma=5.0) == (0.0, -1)
    # 12 sigmas
    assert level_drop(_dip(sigma=5.0) - np.where(np.arange(80) > 60, 60.0, 0.0), sigma=5.0)[1] in (59, 60, 61)
