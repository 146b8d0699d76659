"""A level that falls during the dips (a leak, evaporation, a level sensor drifting down).

Preprocessing makes each dip's submerged volume monotone (isotonic regression), so a falling level
leaves no trace in the slabs: the monotone fit flattens every fall into a plateau, and the profiles
still sum to one volume, only a smaller one (a drift of -0.003 mm/s lost 23 % of a shape's volume
while every consistency check passed). What it leaves is in the readings: once the object is under,
the level must stay put, and it falls instead. Per dip, :func:`tail_slope` is the least-squares
slope of the readings after the monotone fit reached its final value (the object under), in volume
per reading; :func:`level_fall` turns the dips' slopes into the share of the measured volume such a
fall takes over a whole dip, and the number of standard errors by which the slopes lie below 0. A
rising level is the other sign of the same fault; it adds a floor to every slab, which
:func:`dipnet.evaluation.consistency.profile_floor` finds.

Without a fall the tail slopes scatter about 0 or below, since the tail starts ``TAIL_SIGMAS`` noise
sigmas under the fit's end, where the rise still counts: simulated dips of the chamber box and the
bunny, noise-free to 0 dB, gave shares of -8.6 % to 0.0 %; a fall of 0.0005 mm/s at 30 dB gave 3.8 %
(chamber box; 4.8 % of its volume lost) and 19 % (bunny; 14.5 % lost), at 20-66 standard errors. The
authors' recording of three cats: -8.7 % (25 of its 32 dips end before the cats are under).
"""

from __future__ import annotations

import numpy as np

#: Fewest readings after the object is under for a dip's slope.
MIN_TAIL_READINGS = 5
#: The tail starts where the monotone fit is within this many noise sigmas of its final value.
TAIL_SIGMAS = 3.0


def tail_slope(volume: np.ndarray, fitted: np.ndarray, min_readings: int = MIN_TAIL_READINGS) -> float:
    """The least-squares slope (volume per reading) of ``volume[p:]``, ``p`` the first reading at which
    the monotone fit ``fitted`` (same shape ``(R,)``) reaches its final value; NaN with fewer than
    ``min_readings`` readings there.

    Args:
        volume: one dip's submerged volumes from its readings, in reading order ``(R,)`` (mm^3; mm^2 in 2D).
        fitted: their monotone (isotonic) fit ``(R,)``.
    """
    volume, fitted = np.asarray(volume, dtype=np.float64), np.asarray(fitted, dtype=np.float64)
    if volume.shape != fitted.shape or volume.ndim != 1:
        raise ValueError(f"volume and fitted must be one dip's readings of one shape, "
                         f"got {volume.shape} and {fitted.shape}")
    if volume.size == 0:
        return float("nan")
    noise = reading_noise(volume)
    start = int(np.argmax(fitted >= fitted[-1] - TAIL_SIGMAS * noise - 1e-9 * max(1.0, float(np.abs(fitted).max()))))
    tail = volume[start:]
    if tail.size < max(2, int(min_readings)):
        return float("nan")
    return least_squares_slope(tail)


def least_squares_slope(values: np.ndarray) -> float:
    """The least-squares slope of ``values`` ``(R,)`` against their index (value unit per reading); NaN with
    fewer than 2."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < 2:
        return float("nan")
    index = np.arange(values.size, dtype=np.float64) - (values.size - 1) / 2
    return float(np.dot(index, values - values.mean()) / np.dot(index, index))


def level_fall(slopes: np.ndarray, readings: np.ndarray, measured_volume: float) -> tuple[float, float]:
    """``(share, sigmas)`` of the dips' tail slopes (:func:`tail_slope`; NaN ones left out).

    ``share`` = ``-median(slopes) * median(readings) / measured_volume``: the volume a fall at the
    median slope takes over a dip of the median number of readings, as a share of the measured
    volume (positive for a falling level). ``sigmas`` = ``-median(slopes)`` over its standard error
    (``1.2533 * 1.4826 * MAD / sqrt(K)`` of the ``K`` slopes; ``inf`` when they all agree exactly and
    lie below 0, as noise-free data give). Both NaN with fewer than 3 slopes.

    Args:
        slopes: ``(K,)`` per-dip tail slopes (volume per reading).
        readings: ``(K,)`` readings per dip.
        measured_volume: the measured volume (mm^3; mm^2 in 2D), > 0.
    """
    slopes, readings = np.asarray(slopes, dtype=np.float64), np.asarray(readings, dtype=np.float64)
    keep = np.isfinite(slopes)
    if keep.sum() < 3 or not measured_volume > 0:
        return float("nan"), float("nan")
    slopes, readings = slopes[keep], readings[keep]
    fall = -float(np.median(slopes))
    share = fall * float(np.median(readings)) / float(measured_volume)
    error = 1.2533 * 1.4826 * float(np.median(np.abs(slopes + fall))) / np.sqrt(slopes.size)
    if error > 0:
        return share, fall / error
    return share, (float("inf") if fall > 0 else 0.0)


def reading_noise(volume: np.ndarray) -> float:
    """A robust estimate of the white noise of one dip's readings ``(R,)`` (same unit): the MAD of
    their second differences (``sqrt(6)`` noise sigmas each, wherever the volume curves slowly); 0
    with fewer than 3 readings."""
    volume = np.asarray(volume, dtype=np.float64)
    if volume.size < 3:
        return 0.0
    return 1.4826 * float(np.median(np.abs(np.diff(volume, 2)))) / np.sqrt(6.0)


#: Readings on each side of a fall whose medians are compared (:func:`level_drop`): a fall must last this long.
FALL_WINDOW = 3
#: A fall counts when it exceeds this many noise sigmas (and the reading quantum).
FALL_SIGMAS = 6.0


def level_drop(values: np.ndarray, sigma: float = 0.0, quantum: float = 0.0) -> tuple[float, int]:
    """``(drop, index)``: the largest fall of one dip's readings that lasts, and the last reading before it;
    ``(0.0, -1)`` when no fall exceeds :data:`FALL_SIGMAS` noise sigmas plus the quantum (and a billionth of the
    readings' size, their rounding when noise-free).

    The fall at ``i`` is the median of the :data:`FALL_WINDOW` readings up to ``i`` minus the median of the
    :data:`FALL_WINDOW` after it, so a single glitch moves neither median. While the object goes down the level
    only rises, unless water pours into a cavity of the object that was dry (a vessel reaching its rim:
    :mod:`dipnet.simulator.pockets`), the object is lifted, or the tank loses water quickly.

    Args:
        values: one dip's readings in stage order ``(R,)`` (reading units, e.g. mm of level).
        sigma: the readings' stated noise (same unit); the larger of it and :func:`reading_noise` is used.
        quantum: the sensor's reading step (same unit).
    """
    values = np.asarray(values, dtype=np.float64)
    if values.size < 2 * FALL_WINDOW:
        return 0.0, -1
    medians = np.median(np.lib.stride_tricks.sliding_window_view(values, FALL_WINDOW), axis=1)
    falls = medians[: values.size - 2 * FALL_WINDOW + 1] - medians[FALL_WINDOW:]
    at = int(np.argmax(falls))
    noise = max(float(sigma), reading_noise(values))
    rounding = 1e-9 * float(np.abs(values).max())  # noise-free readings still differ in their last bits
    if not falls[at] > FALL_SIGMAS * noise + quantum + rounding:
        return 0.0, -1
    return float(falls[at]), at + FALL_WINDOW - 1
