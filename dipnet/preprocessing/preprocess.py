"""Preprocessing: a :class:`~dipnet.core.rawscan.RawScan` -> a :class:`~dipnet.core.measurement.DipMeasurement`.

Per orientation:

0. outlier readings (level spikes and drops) are repaired or the dip rejected
   (:func:`dipnet.preprocessing.readings.repair_readings`; the decisions go into ``metadata["readings"]``);
1. drop flagged readings (default ``"unstable"``), average repeated stage positions;
2. baseline: the mean of the readings before the level starts to rise (at least the first);
3. reading -> submerged volume ``C_i``: level rise x tank cross-section ``A`` (or balance
   reading / density); the water rise is ``delta_i = C_i / A``;
4. make ``C`` monotone (isotonic regression, the least-squares monotone fit); the slope of the
   readings after the fit reached its final value (the object under, where the level must stay put)
   goes into ``metadata["tail_slope"]`` (:func:`dipnet.preprocessing.level_trend.tail_slope`), since
   the fit hides a falling level (a leak) from the profiles, and so does a fall that lasts while the object
   goes down (a cavity flooding): ``metadata["level_drop"]`` per dip ``[volume (mm^3), stage (mm)]``
   (:func:`~dipnet.preprocessing.level_trend.level_drop`; ``[0, None]`` without one);
5. water line height in the object frame ``t_i = t_start + s_i + delta_i`` (``s_i`` = stage
   position). ``t_start`` (the water line at stage 0) comes from the scan's metadata
   (simulated scans, calibrated rigs), or is estimated: ``"centroid"`` puts the profile's
   centroid at ``c . theta`` (``c`` = the object centre, default the origin; exact, since the
   first moment of a dip profile is ``V c_obj . theta``), ``"onset"`` puts the height where
   the object touches the water at the lowest slab edge (the authors' choice);
6. uniform slabs: the cumulative volume ``C(t)`` is interpolated monotonically
   (``scipy.interpolate.PchipInterpolator``, constant outside the scanned range) at the slab
   edges (default: the grid's ``[-L/2, L/2]`` in ``M`` slabs, the operator's slabs) and
   differenced; the share of each dip's volume below the first edge and above the last (cut off from
   the profiles: the object reaches beyond the grid, or the level drifts) goes into
   ``metadata["outside_share"]``, the height the readings span there (mm) into ``metadata["outside_mm"]``,
   and a share above :data:`~dipnet.core.measurement.BEYOND_SLABS_TOL` (and the noise's) is warned about;
   how far the object reaches goes into ``metadata["reach_mm"]`` (:func:`reach_from_readings`: per dip the
   heights ``[low, high]`` with some of its volume below ``low`` and above ``high``, from the readings
   themselves, so neither the slabs nor the interpolation between readings widen it), which validation
   compares with the grid's working ball;
7. optional smoothing with the paper's normalised 5-tap ``gausswin`` (alpha = 2.5), with
   half-sample symmetric reflection at the ends so no volume is lost.

Noise: when the reading noise ``sigma_r`` is known (orientation ``meta["noise_sigma"]`` or the
header) the cumulative volume at each edge is modelled with independent errors of standard
deviation ``c = k sqrt(sigma_r^2 + q^2 / 12)`` (``k`` = ``A`` or ``1 / density``, ``q`` = the
header's ``resolution``); slab sigma is ``c sqrt(diag(S D D^T S^T))`` with ``D`` the
difference and ``S`` the smoothing matrix (approximate: it ignores the monotone fit and
correlations when slabs are thinner than a stage step). The readings' own noise (their third
differences, :func:`~dipnet.preprocessing.validation.reading_noise`) goes into
``metadata["reading_noise_volume"]`` (``k`` times it, the volume of one reading's noise) and the stated
noise over it into ``metadata["reading_noise_ratio"]`` (``None`` when no noise is stated), which the
consistency check compares; ``metadata["reading_noise_leak"]``
(:func:`~dipnet.preprocessing.validation.reading_noise_leak`) says whether that estimate holds the rise too.
When a dip states no noise and the estimate holds the noise alone (a leak below
:data:`~dipnet.preprocessing.validation.NOISE_LEAK_MAX`), ``metadata["readings_slab_sigma"]`` is the per-slab
sigma it gives (mm^3: the volume of one reading's noise times the slab gain ``sqrt(diag(S D D^T S^T))``, ``sqrt(2)``
unsmoothed), which the optimising solvers take for an unstated noise (:func:`dipnet.solvers.base.noise_sigma`);
else ``None``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.ndimage
import scipy.optimize
from scipy.interpolate import PchipInterpolator

from dipnet.core.counts import is_real
from dipnet.core.geometry import CROSS_SECTION_RANGE_MM2
from dipnet.core.grid import Grid, slab_count
from dipnet.core.measurement import BEYOND_SLABS_TOL, REACH_SIGMAS, DipMeasurement
from dipnet.core.strict_json import finite_or_none
from dipnet.core.rawscan import OrientationScan, RawScan, complete_dips, naming_file, read_rawscan
from dipnet.core.warn import log_and_warn
from dipnet.preprocessing.level_trend import MIN_TAIL_READINGS, least_squares_slope, level_drop, tail_slope
from dipnet.preprocessing.readings import ReadingsReport, max_object_section, repair_readings
from dipnet.preprocessing.validation import NOISE_LEAK_MAX, reading_noise, reading_noise_leak

log = logging.getLogger(__name__)

T_START_METHODS = ("auto", "metadata", "centroid", "onset")
#: The smallest tolerance of :func:`reach_from_readings`, relative to the dip's largest volume: a noise-free dip
#: (tolerance 0) whose monotone fit ends 5e-13 mm^2 short of its final volume for a few readings (a 2D square's
#: edge-on dip) put the object's top 20 mm too high and was refused as larger than the working ball.
REACH_ROUNDOFF = 1e-9


def gausswin(n: int = 5, alpha: float = 2.5) -> np.ndarray:
    """MATLAB's ``gausswin(n, alpha)`` normalised to sum 1, ``(n,)`` float64.

    ``gausswin(5)`` gives ``[0.02193, 0.22851, 0.49912, 0.22851, 0.02193]``.
    """
    k = np.arange(n) - (n - 1) / 2
    w = np.exp(-0.5 * (alpha * k / ((n - 1) / 2)) ** 2)
    return w / w.sum()


def smooth_profiles(profiles: np.ndarray, kernel: np.ndarray | None = None) -> np.ndarray:
    """Smooth slab volumes ``(..., M)`` along the last axis, conserving each profile's sum.

    Half-sample symmetric reflection at both ends with a symmetric kernel gives a symmetric
    smoothing matrix whose columns sum to one, so no volume is lost at the ends.
    """
    kernel = gausswin() if kernel is None else np.asarray(kernel, dtype=np.float64)
    return scipy.ndimage.convolve1d(np.asarray(profiles, dtype=np.float64), kernel, axis=-1, mode="reflect")


def slab_edges(grid: Grid, n_slabs: int | None = None) -> np.ndarray:
    """The operator's slab edges for ``grid``: ``[-L/2, L/2]`` in ``M`` slabs, ``(M + 1,)`` mm
    (``M`` = ``n_slabs``, default ``grid.n``; :func:`~dipnet.core.grid.slab_count` checks it)."""
    return np.linspace(-grid.extent / 2, grid.extent / 2, slab_count(grid, n_slabs) + 1)


def level_drift_removed(raw: RawScan, drift_mm_per_s: float) -> RawScan:
    """A copy of a level scan ``raw`` whose readings drift ``drift_mm_per_s`` (mm/s) less (its readings' time from
    the session start); ``raw`` itself for a balance or no drift."""
    if not drift_mm_per_s or raw.header.quantity != "level_mm":
        return raw
    return replace(raw, orientations=[replace(o, values=o.values - drift_mm_per_s * o.time_s)
                                      for o in raw.orientations])


def repair_without_drift(raw: RawScan, drift_mm_per_s: float, **options) -> tuple[RawScan, ReadingsReport]:
    """:func:`~dipnet.preprocessing.readings.repair_readings` (``options``) on a level scan's readings with the level
    drift ``drift_mm_per_s`` (mm/s) taken out, which is then put back: the copy and the report.

    A level that drifts by more than the noise over a dip's rest readings leaves the dip's first readings below
    its start, which the range test takes for outliers: a hammer of 2,000 mm^3 in a tank of 84,000 mm^2 with a
    drift of -3e-5 mm/s (1.4 mm over the session) had 86 of its 100 dips rejected at 30 dB (82 at 20 dB), and
    calibration went on from the other 14.
    """
    repaired, report = repair_readings(level_drift_removed(raw, drift_mm_per_s), **options)
    return level_drift_removed(repaired, -drift_mm_per_s), report


def preprocess(raw: RawScan, *, edges=None, grid: Grid | None = None, n_slabs: int | None = None,
               cross_section_mm2: float | None = None, t_start: str | float = "auto",
               object_centre=None, smooth: bool = False, drop_flags=("unstable",),
               onset_tol: float | None = None, include_incomplete: bool = False,
               repair: bool = True, check_step: bool = True) -> DipMeasurement:
    """Turn a raw scan into uniform slab volumes.

    Args:
        raw: the raw scan.
        edges: uniform slab edges ``(M + 1,)`` mm shared by all orientations; default from
            ``grid`` and ``n_slabs`` (:func:`slab_edges`).
        grid, n_slabs: the reconstruction grid and slab count (when ``edges`` is not given).
        cross_section_mm2: tank free cross-section ``A`` (mm^2; mm in 2D); default the header's. Either must lie
            in :data:`~dipnet.core.geometry.CROSS_SECTION_RANGE_MM2` (else a ``ValueError``: wrong units).
        t_start: ``"metadata"`` | ``"centroid"`` | ``"onset"`` | a number (mm) | ``"auto"``
            (``"metadata"`` when the scan records it, else ``"centroid"``). See module docstring.
        object_centre: the object centre ``(ndim,)`` mm for ``"centroid"`` (default the origin).
        smooth: apply the 5-tap Gaussian (:func:`smooth_profiles`).
        drop_flags: readings carrying any of these flags are ignored.
        onset_tol: rise (reading units) that marks the onset of contact; default
            ``3 sigma_r`` plus one resolution step (a tiny fraction of the total rise if neither
            is known).
        include_incomplete: also use orientations whose scan did not finish (default: skip
            them with a warning).
        repair: repair outlier readings or reject their dips first
            (:func:`dipnet.preprocessing.readings.repair_readings`, bounded by the grid's working ball when
            ``grid`` is given); ``False`` when the caller already did.
        check_step: refuse a stage step too coarse for the slabs and warn about one thicker than a slab
            (:func:`check_stage_step`); ``False`` when the caller already did (a calibration, once per scan rather
            than once per trial geometry).

    Returns:
        ``DipMeasurement`` with profiles ``(K, M)`` (mm^3; mm^2 in 2D), ``offsets = edges[0]``,
        per-slab ``sigma`` when the reading noise is known, and provenance metadata
        (``orientation_k``, ``t_start_mm``, ``tail_slope`` (volume per reading) and ``readings_per_dip``
        per orientation, ``outside_share`` and ``outside_mm`` per orientation (the share of its volume beyond
        the slab edges and the height its readings span there), ``reach_mm`` per orientation
        (:func:`reach_from_readings`), ``reading_quantum`` (reading units) and ``reading_quantum_volume`` (mm^3) when
        the scan records its resolution, ``readings``: the outlier report, ...).
    """
    report = ReadingsReport()
    edges = _resolve_edges(edges, grid, n_slabs)
    if repair:
        raw, report = repair_readings(raw, max_cross_section=None if grid is None else max_object_section(grid),
                                      slab_mm=float(edges[1] - edges[0]))
    header = raw.header
    if check_step:
        check_stage_step(raw, float(edges[1] - edges[0]))
    area = cross_section_mm2 if cross_section_mm2 is not None else header.tank_cross_section_mm2
    if area is None:
        raise ValueError("the tank cross-section is unknown: pass cross_section_mm2 (mm^2; mm in 2D)")
    low, high = CROSS_SECTION_RANGE_MM2
    if not is_real(area) or not low <= area <= high:  # NaN fails too
        source = "cross_section_mm2" if cross_section_mm2 is not None else "the scan header's tank_cross_section_mm2"
        raise ValueError(f"the tank cross-section {area!r} ({source}) is outside [{low:g}, {high:g}] mm^2 (mm in 2D): "
                         "wrong units?")
    if (t_start not in T_START_METHODS if isinstance(t_start, str)
            else not is_real(t_start) or not math.isfinite(t_start)):
        raise ValueError(f"t_start must be a finite number (mm) or one of {T_START_METHODS}, got {t_start!r}")
    scans = raw.orientations if include_incomplete else complete_dips(raw)
    if not scans:
        raise ValueError(f"the raw scan{'' if raw.path is None else ' ' + str(raw.path)} has no orientation")
    # ``scale`` turns a reading difference into a volume: x A (level) or / density (balance)
    scale = float(area) if header.quantity == "level_mm" else 1.0 / header.density_g_per_mm3
    centre = np.zeros(header.ndim) if object_centre is None else np.asarray(object_centre, dtype=np.float64)

    profiles, starts, sigmas, slopes, counts, outside, outside_mm = [], [], [], [], [], [], []
    readings, stated, curves, drops = [], [], [], []
    for o in scans:
        stage, values = _clean_readings(o, drop_flags)
        noise = o.meta.get("noise_sigma", header.noise_sigma)
        readings.append(values)
        stated.append(noise)
        quantum = header.resolution or 0.0
        drop, at = level_drop(values, noise or 0.0, quantum)
        drops.append([scale * drop, float(stage[at]) if drop > 0 else None])
        tol = onset_tol if onset_tol is not None else _default_tol(values, noise, quantum)
        onset = onset_index(values, tol)
        baseline = values[: max(1, onset - 1)].mean()
        rise = scale * (values - baseline)
        volume = scipy.optimize.isotonic_regression(rise).x
        slopes.append(tail_slope(rise, volume))
        counts.append(len(values))
        u = stage + volume / float(area)  # t - t_start, strictly increasing
        t0 = _start_height(o, header, t_start, u, volume, onset, edges, centre)
        curve = PchipInterpolator(t0 + u, volume, extrapolate=False)
        cum = curve(np.clip(edges, t0 + u[0], t0 + u[-1]))
        profiles.append(np.maximum(np.diff(cum), 0.0))
        outside.append(_outside_share(cum, volume))
        outside_mm.append(max(edges[0] - t0 - u[0], 0.0) + max(t0 + u[-1] - edges[-1], 0.0))
        starts.append(t0)
        curves.append((t0 + u, volume))
        sigmas.append(None if noise is None else scale * float(np.hypot(noise, quantum / np.sqrt(12.0))))
    _warn_outside(outside, [o.k for o in scans], sigmas, [float(p.sum()) for p in profiles], edges)
    read_sigma, read_ratio = reading_noise(readings, stated, header.resolution or 0.0)
    reach = [reach_from_readings(t, v, REACH_SIGMAS * max(s or 0.0, scale * np.nan_to_num(read_sigma)),
                                 slope if np.isfinite(slope) else _end_slope(v))
             for (t, v), s, slope in zip(curves, sigmas, slopes)]
    leak = reading_noise_leak(readings)
    # no stated noise: the slab noise the readings' scatter gives, when their estimate holds the noise alone
    unit_sigma = _unit_slab_sigma(len(edges) - 1, smooth)  # a slab's sigma per unit noise of the cumulative volume
    readings_sigma = (scale * read_sigma * float(np.median(unit_sigma))
                      if any(s is None for s in stated) and read_sigma > 0 and leak < NOISE_LEAK_MAX
                      else None)  # NaN compares False

    prof = np.stack(profiles)
    if smooth:
        prof = smooth_profiles(prof)
    sigma = None
    if all(s is not None and s > 0 for s in sigmas):
        sigma = np.asarray(sigmas)[:, None] * unit_sigma[None, :]
    return DipMeasurement(
        directions=np.stack([o.unit_direction for o in scans]), profiles=prof,
        slab_thickness=float(edges[1] - edges[0]), offsets=np.full(len(scans), edges[0]), sigma=sigma,
        metadata={"source": "rawscan", "rawscan": None if raw.path is None else str(raw.path),
                  "rig": header.rig, "quantity": header.quantity, "tank_cross_section_mm2": float(area),
                  "t_start": t_start if isinstance(t_start, str) else "given",
                  "t_start_mm": [float(t) for t in starts], "smoothed": bool(smooth),
                  "orientation_k": [o.k for o in scans], "scan_metadata": header.metadata,
                  "tail_slope": [float(v) for v in slopes], "readings_per_dip": counts, "level_drop": drops,
                  "outside_share": outside, "outside_mm": [float(v) for v in outside_mm],
                  "reach_mm": [[finite_or_none(v) for v in row] for row in reach],
                  "reading_quantum": header.resolution, "reading_quantum_volume":
                      None if header.resolution is None else scale * float(header.resolution),
                  "reading_noise_volume": finite_or_none(scale * read_sigma),
                  "reading_noise_ratio": finite_or_none(read_ratio), "reading_noise_leak": finite_or_none(leak),
                  "readings_slab_sigma": finite_or_none(readings_sigma),
                  "readings": report.to_json()})


def preprocess_file(path: str | Path, **options) -> DipMeasurement:
    """:func:`preprocess` applied to the raw scan file at ``path`` (:func:`~dipnet.core.rawscan.read_rawscan`)."""
    with naming_file(path):
        return preprocess(read_rawscan(path), **options)


# --------------------------------------------------------------------------- helpers
#: A stage step more than this many slabs thick is refused: the readings cannot resolve the profiles.
MAX_STEP_IN_SLABS = 4.0


def _stage_step(raw: RawScan) -> float | None:
    """The median stage step (mm) over the dips' readings, or ``None`` without two readings."""
    steps = [np.diff(np.unique(o.stage_mm)) for o in raw.orientations if len(o.stage_mm) > 1]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    return float(np.median(steps)) if steps.size else None


def check_stage_step(raw: RawScan, slab_mm: float) -> None:
    """What :func:`preprocess` checks of ``raw``'s stage step against slabs ``slab_mm`` thick (mm): refused over
    :data:`MAX_STEP_IN_SLABS` slabs, warned about over one. For a caller that preprocesses one scan many times
    (a calibration's trial geometries) and so checks it once, passing ``check_step=False`` to every trial."""
    _check_step(_stage_step(raw), float(slab_mm))


def _check_step(step_mm: float | None, slab_mm: float) -> None:
    """Refuse a stage step over :data:`MAX_STEP_IN_SLABS` slabs; warn over one (profiles interpolated)."""
    if step_mm is None or not step_mm > slab_mm:
        return
    found = f"the stage step ({step_mm:.4g} mm) is {step_mm / slab_mm:.3g} slabs thick (slab {slab_mm:.4g} mm)"
    if step_mm > MAX_STEP_IN_SLABS * slab_mm:
        raise ValueError(f"{found}: the readings cannot resolve the profiles (an object far smaller than the "
                         "step: a mesh in metres needs shape.scale=1000; else a smaller protocol.step_mm or a "
                         "lower resolution)")
    message = f"{found}: the profiles between readings are interpolated"
    log_and_warn(log, message, stacklevel=3)


def reach_from_readings(heights: np.ndarray, volume: np.ndarray, tol: float, drift: float = 0.0
                        ) -> tuple[float, float]:
    """How far one dip's object certainly reaches: ``(low, high)`` heights (mm, object frame) of the first reading
    whose submerged volume exceeds ``tol`` (some of the object lies below it) and of the last whose volume falls
    short of the final one by more than ``tol`` (some lies above it); NaN for either when no reading does. A level
    rising in time adds ``drift`` per reading before the object touches and after it is under, which an object
    beyond would add too: twice what it adds over the readings before (after) a reading joins ``tol`` there.

    A slab's volume cannot say this as well: the cumulative volume is interpolated between readings, so a slab
    beyond the object's end may hold part of the last step's rise (a ball as large as the working ball, read at
    5 mm steps onto 4.1 mm slabs, put 2 % of its largest slab beyond the ball).

    Args:
        heights: the water line's heights at the readings ``(R,)``, mm, increasing.
        volume: the submerged volume there ``(R,)`` (the monotone fit over the level before contact, mm^3; mm^2
            in 2D).
        tol: the volume (same unit) a difference must exceed: a few noise sigmas of a reading (at least
            :data:`REACH_ROUNDOFF` of the largest volume, so that round-off does not count as volume).
        drift: the level's rise per reading once the object is under (same unit;
            :func:`~dipnet.preprocessing.level_trend.tail_slope`); a fall or NaN counts as none.
    """
    count = np.arange(volume.size, dtype=np.float64)
    if volume.size:
        tol = max(float(tol), REACH_ROUNDOFF * float(np.abs(volume).max()))
    rising = 2.0 * max(float(np.nan_to_num(drift)), 0.0)
    below = np.flatnonzero(volume > tol + rising * count)
    above = np.flatnonzero(volume < volume[-1] - tol - rising * count[::-1])
    return (float(heights[below[0]]) if below.size else float("nan"),
            float(heights[above[-1]]) if above.size else float("nan"))


def _end_slope(volume: np.ndarray, n: int = MIN_TAIL_READINGS) -> float:
    """The least-squares slope (volume per reading) of the last ``n`` of one dip's ``volume`` ``(R,)``: a level
    still rising where the monotone fit never levels off (a fast drift, or a dip ended before the object is under);
    NaN with fewer than 2 readings."""
    return least_squares_slope(np.asarray(volume, dtype=np.float64)[-n:])


def _outside_share(cum: np.ndarray, volume: np.ndarray) -> float:
    """The share of a dip's volume (the monotone fit ``volume``, mm^3) outside the slab edges, where its
    cumulative volume is ``cum`` ``(M + 1,)`` mm^3: below the first edge and above the last; 0 for no rise."""
    total = float(volume[-1] - volume[0])
    return max(0.0, 1.0 - float(cum[-1] - cum[0]) / total) if total > 0 else 0.0


def _warn_outside(shares: list[float], ks: list[int], sigmas: list[float | None], inside: list[float],
                  edges: np.ndarray) -> None:
    """Warn once when a dip's share of volume beyond the slab edges (``shares``) exceeds
    :data:`~dipnet.core.measurement.BEYOND_SLABS_TOL` and 3 times the noise of a cumulative volume
    (``sigmas``, mm^3, ``None`` when unknown) over the dip's volume (``inside`` / (1 - share), mm^3)."""
    limits = [max(BEYOND_SLABS_TOL, 0.0 if s is None else 3.0 * s * (1.0 - f) / max(v, 1e-300))
              for f, s, v in zip(shares, sigmas, inside)]
    over = [i for i, (f, limit) in enumerate(zip(shares, limits)) if f > limit]
    if not over:
        return
    worst = max(over, key=lambda i: shares[i])
    message = (f"{len(over)} of {len(shares)} dips hold more than {BEYOND_SLABS_TOL:.0%} of their volume outside the "
               f"slabs [{edges[0]:.1f}, {edges[-1]:.1f}] mm (up to {shares[worst]:.1%}, orientation {ks[worst]}), "
               "which the profiles leave out: the object reaches beyond the grid, and extent_mm must grow to hold "
               "it (or a level drifting in time rises there, or a wrong rig geometry misplaces the dips' heights)")
    log_and_warn(log, message, stacklevel=3)


def _resolve_edges(edges, grid: Grid | None, n_slabs: int | None) -> np.ndarray:
    if edges is None:
        if grid is None:
            raise ValueError("give the slab edges or the reconstruction grid (and n_slabs)")
        return slab_edges(grid, n_slabs)
    edges = np.asarray(edges, dtype=np.float64).reshape(-1)
    steps = np.diff(edges)
    if len(edges) < 3 or not (steps > 0).all() or not np.allclose(steps, steps[0], rtol=1e-9, atol=0):
        raise ValueError("slab edges must be at least 3 increasing, equally spaced heights (mm)")
    return edges


def _clean_readings(o: OrientationScan, drop_flags) -> tuple[np.ndarray, np.ndarray]:
    """Unflagged readings sorted by stage, repeated stage positions averaged: ``(stage, values)``."""
    keep = np.array([not (set(f) & set(drop_flags)) for f in o.flags], dtype=bool)
    if keep.sum() < 2:
        raise ValueError(f"orientation {o.k} has fewer than 2 usable readings")
    stage, inverse = np.unique(o.stage_mm[keep], return_inverse=True)
    values = np.bincount(inverse, weights=o.values[keep]) / np.bincount(inverse)
    if len(stage) < 2:
        raise ValueError(f"orientation {o.k}: all readings were taken at one stage position")
    return stage, values


def _default_tol(values: np.ndarray, noise: float | None, quantum: float) -> float:
    tol = 3.0 * (noise or 0.0) + quantum
    return tol if tol > 0 else 1e-9 * max(float(np.ptp(values)), 1e-300)


def onset_index(values: np.ndarray, tol: float) -> int:
    """Index of the first reading more than ``tol`` above the first one (``len`` if none)."""
    above = np.flatnonzero(values - values[0] > tol)
    return int(above[0]) if above.size else len(values)


def _start_height(o: OrientationScan, header, method, u, volume, onset, edges, centre) -> float:
    """The water line height ``t_start`` (mm, object frame) at stage 0 for one orientation."""
    if not isinstance(method, str):
        return float(method)
    recorded = o.meta.get("t_start_mm", header.t_start_mm)
    if method == "metadata" or (method == "auto" and recorded is not None):
        if recorded is None:
            raise ValueError(f"orientation {o.k}: the scan does not record t_start_mm; use t_start='centroid'")
        return float(recorded)
    if method == "onset":
        return float(edges[0] - u[max(onset - 1, 0)])
    gained = np.diff(volume)
    if gained.sum() <= 0:
        raise ValueError(f"orientation {o.k}: the reading never rises, cannot place the profile")
    centroid = float(np.sum(0.5 * (u[1:] + u[:-1]) * gained) / gained.sum())
    return float(centre @ o.unit_direction) - centroid


def _unit_slab_sigma(m: int, smooth: bool) -> np.ndarray:
    """``sqrt(diag(S D D^T S^T))`` for unit-variance independent errors at the ``m + 1`` edges."""
    d = np.diff(np.eye(m + 1), axis=0)  # (m, m + 1): slab = C(e_{j+1}) - C(e_j)
    if smooth:
        d = smooth_profiles(d.T).T
    return np.sqrt((d**2).sum(axis=1))
