"""The grid-free stage of rig calibration: dip moments, a global search and a bootstrap over dips.

Every complete dip of a rigid object obeys two range conditions of the Radon transform,
whatever the object's shape (Helgason-Ludwig, orders 0-2). With ``u_i = s x stage_i + rise_i``
(the water line relative to its stage-0 height, mm; ``s`` = :attr:`RigGeometry.step_scale`)
and the level rises ``w_i`` as weights, the dip's centroid and variance are

    t_start_k + mean_w(u)  =  c . theta_k                    (first moment)
    var_w(u)               =  theta_k^T S theta_k            (second central moment)

with ``c`` the object's centroid (mm), ``S`` its volume covariance (mm^2), ``theta_k`` the
true direction of dip ``k`` and ``t_start_k = t0 + p (cos r - 1) + e sin r`` its true start
height (:meth:`RigGeometry.start_heights`, ``r`` the true tilt). These need no grid and no
shape, so nothing is cut off or rejected before the geometry is known, and they are cheap
enough for a global search and a bootstrap:

* ``c``, ``S``, the pivot ``p``, the tilt-axis offset ``e`` (and ``t0`` when free) enter
  linearly and are solved for in closed form (variable projection); the tilt zero, spin zero
  and step scale are searched on a grid first (:func:`fit_moments`), then refined by least
  squares, so start heights 50+ mm off never trap a local fit;
* for a reference object ``c`` and ``S`` are known (a ball of radius ``R`` centred at ``c``:
  ``S = R^2 / 5 I``) and the object's volume gives the tank's cross-section;
* level drift is fitted first, from the baselines (:func:`fit_drift`): the level before
  contact (:func:`rest_readings`) is the same rest level in every dip, so its trend over the
  session is the drift.

What the data cannot tell, the fit finds flat or degenerate (:data:`GAUGE_REASONS`):

* self-calibration: the spin zero is the object's own rotation about the spin axis, and the
  step scale is the scale of the whole scene (object, pivot, offset: the first moments are
  exactly invariant; the rises break it only at second order);
* a reference object symmetric about the spin axis (a centred ball): its symmetry hides the
  spin zero, and with pivot and offset near 0 also the tilt zero.

Uncertainty: the 90% intervals are percentiles of a bootstrap over dips (each refit from the
estimate with dips drawn with replacement), which carries the model error of the moments
(discretisation, lag, noise, a shape the moments describe imperfectly) instead of assuming
white noise; a parameter is *determined* when its interval is narrower than its tolerance.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.optimize
import torch

from dipnet.core.geometry import RigGeometry, scan_geometry
from dipnet.core.rawscan import OrientationScan, RawScan, complete_dips
from dipnet.preprocessing.preprocess import onset_index, repair_without_drift
from dipnet.preprocessing.readings import MAD_TO_SIGMA

log = logging.getLogger(__name__)

#: The parameters the moment stage estimates (RigGeometry fields plus ``t0_mm``, a common
#: offset of every dip's start height). The cross-section needs a known volume (reference).
MOMENT_PARAMETERS = ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale", "t0_mm")
#: A reference object's nuisances known to a tolerance (:class:`MomentModel`'s ``priors``): the common start
#: height and the object's centre moved along x, y, z of the object frame (its mounting).
NUISANCES = ("t0_mm", "shift_x_mm", "shift_y_mm", "shift_z_mm")
#: The start height's model error (mm, standard deviation): what the moments' discretisation puts into every dip's
#: first moment alike, added (in quadrature) to a reference object's start-height tolerance. With a 30 mm ball
#: held exactly where assumed (no sensor lag, 30 dB, 60 random rigs of the calibration benchmark's range, seed 7)
#: 0.06 covers the centred ball's tilt zero and offset at 100 % and 97 % (0.03, measured on 30 of the rigs
#: before Sheppard's correction: 80 % and 70 %).
START_MODEL_SD_MM = 0.06
#: Search grid of the nonlinear parameters: half-width and step (the calibrated range).
SEARCH = {"tilt_zero_deg": (6.0, 0.5), "spin_zero_deg": (6.0, 1.0), "step_scale": (0.05, 0.005)}
#: The fewest spare conditions (the dips' moment conditions less the unknowns, :func:`spare_conditions`) the
#: moment stage needs: with none the moments are fitted exactly at any grid point near the truth, and every
#: bootstrap refit of the same few dips returns that point (6 dips of an unknown object: a tilt zero 4.5 deg
#: off with an interval of +-0.02 deg).
MIN_SPARE_CONDITIONS = 3
#: A parameter is determined when the half-width of its 90% interval is below this.
TOLERANCE = {"pivot_mm": 2.5, "tilt_axis_offset_mm": 1.5, "tilt_zero_deg": 0.5, "spin_zero_deg": 0.5,
             "step_scale": 0.005, "t0_mm": 1.0, "cross_section_mm2": 0.10, "level_drift_mm_per_s": 2e-5}
GAUGE_REASONS = {
    ("self", "spin_zero_deg"): "the object's own rotation about the spin axis absorbs it: no dip of an unknown "
                               "object can show it (calibrate it with a reference object off the spin axis)",
    ("self", "step_scale"): "the scale of the whole scene: a larger object on a rig with a larger pivot and a longer "
                            "step gives the same dips; only the section / step_scale^3 ratio is fixed by the shape "
                            "(calibrate it with a reference object of known size, or measure the stage travel)",
    ("reference", "spin_zero_deg"): "a reference object symmetric about the spin axis (a centred ball) looks the "
                                    "same at every spin (its symmetry)",
    ("off_axis", "spin_zero_deg"): "a reference off the spin axis shows the spin zero only as well as its sideways "
                                   "position is known (about the position tolerance over its distance from the axis)",
    ("reference", "tilt_zero_deg"): "a centred ball's dips depend on the tilt only through the start heights, which "
                                    "the pivot and offset move too little here, or the start height's tolerance too "
                                    "much, to show the tilt zero",
}
BOOTSTRAP = 200
#: A balance's rises are its displaced volumes over the tank's nominal section, which a reference's dips cannot
#: tell from the step scale (a ball's every dip has the same spread): the true section's relative standard
#: deviation about the nominal one, that of a uniform draw over the calibrated range +-20 %, unless a better one is
#: given (:func:`dip_moments`' ``section_sd``). Drawn in the bootstrap (:func:`fit_moments`): held at the nominal
#: section, a ball's step scale came out 0.39 % low with an interval of +-0.07 % in a tank 10 % larger than nominal
#: (0.70 % low, 17 standard errors, at 20 %).
BALANCE_SECTION_SD = 0.2 / math.sqrt(3.0)


@dataclass
class DipMoments:
    """Per-dip sums of one raw scan, from which the moments follow for any step scale.

    Attributes (all ``(K,)`` float64, mm unless noted):
        tilt_deg, spin_deg: commanded rig angles (degrees).
        t_recorded: the start height each dip recorded, less the height shift the rig applied.
        rise: the total level rise (mm; for a balance: the displaced volume / nominal section).
        a1, b1: rise-weighted means of the stage and of the rise.
        ss, sd, dd: rise-weighted means of stage^2, stage x rise and rise^2 (midpoints of each step).
        rise_scale_sd: how far the rises' scale may be off (relative standard deviation): 0 for a level sensor,
            which reads the rise itself; for a balance, whose rise is the displaced volume over the tank's
            *nominal* section, how well that section is known (by default :data:`BALANCE_SECTION_SD`;
            :func:`fit_moments` draws it in its bootstrap).
        level_gain: the median over the dips of the water line's steepest rise per mm of stage (over three
            steps), ``a / (A - a)`` for an object of largest section ``a`` in a tank of section ``A``: the water
            line then moves ``1 + level_gain`` times the stage step between readings, which the moments' midpoint
            sums take for a uniform slab (:data:`SNUG_LEVEL_GAIN`).
    """

    tilt_deg: np.ndarray
    spin_deg: np.ndarray
    t_recorded: np.ndarray
    rise: np.ndarray
    a1: np.ndarray
    b1: np.ndarray
    ss: np.ndarray
    sd: np.ndarray
    dd: np.ndarray
    k: list[int] = field(default_factory=list)
    rise_scale_sd: float = 0.0
    level_gain: float = 0.0

    def take(self, index: np.ndarray) -> "DipMoments":
        """The moments of the dips ``index`` (a bootstrap draw)."""
        return replace(self, **{f: getattr(self, f)[index] for f in
                                ("tilt_deg", "spin_deg", "t_recorded", "rise", "a1", "b1", "ss", "sd", "dd")},
                       k=[self.k[i] for i in index])

    def rise_scaled(self, scale: float) -> "DipMoments":
        """The moments with every rise ``scale`` times as large (a balance's tank section ``1 / scale`` times the
        nominal one): the rise's sums ``b1``, ``sd`` scale by it, ``dd`` by its square."""
        return replace(self, rise=self.rise * scale, b1=self.b1 * scale, sd=self.sd * scale, dd=self.dd * scale**2)

    def centroid_and_variance(self, step_scale: float) -> tuple[np.ndarray, np.ndarray]:
        """``(mean_w(u), var_w(u))`` per dip (mm, mm^2) for a step scale."""
        mean = step_scale * self.a1 + self.b1
        second = step_scale**2 * self.ss + 2 * step_scale * self.sd + self.dd
        return mean, second - mean**2


def fit_drift(raw: RawScan, bootstrap: int = BOOTSTRAP, seed: int = 0) -> tuple[float, tuple[float, float]]:
    """Level drift (mm/s) from the rest level before contact: a robust line through every dip's
    first readings over the session, and its 90% interval from a bootstrap over dips, at least +-1.645
    standard errors of the line under white noise (:func:`_slope_standard_error`: over 16 dips, where a few at
    the session's end carry the slope, the bootstrap alone came out up to 20 % narrower than the estimates
    scatter) (``(0, (0, 0))`` for a balance or when the readings span no time)."""
    times, levels, dip = [], [], []
    for o in complete_dips(raw):
        if o.time_s.size < 3:
            continue
        before = rest_readings(o)
        times.extend(o.time_s[before])
        levels.extend(o.values[before])
        dip.extend([len(set(dip))] * len(before))
    if len(set(dip)) < 2 or np.ptp(times) <= 0 or raw.header.quantity != "level_mm":
        return 0.0, (0.0, 0.0)
    t, y, dip = np.asarray(times), np.asarray(levels), np.asarray(dip)
    slope = _robust_slope(t, y)
    rng = np.random.default_rng(seed)
    n = int(dip.max()) + 1
    draws = []
    for _ in range(int(bootstrap)):
        rows = np.concatenate([np.flatnonzero(dip == d) for d in rng.integers(0, n, n)])
        if np.ptp(t[rows]) > 0:
            draws.append(_robust_slope(t[rows], y[rows]))
    half = 1.645 * _slope_standard_error(t, y, slope)
    return slope, (float(min(np.percentile(draws, 5), slope - half)),
                   float(max(np.percentile(draws, 95), slope + half)))


def _slope_standard_error(t: np.ndarray, y: np.ndarray, slope: float) -> float:
    """Standard error (mm/s) of the slope of a line through levels ``y`` (mm) at times ``t`` (s) under white
    noise, its sigma from the residuals' median absolute deviation (spikes do not count)."""
    centred = t - t.mean()
    return _mad_sigma(y - slope * centred) / math.sqrt(float(np.dot(centred, centred)))


def reading_sigma(values: np.ndarray) -> float:
    """The white noise ``sigma`` of one dip's readings ``values`` ``(n,)`` (reading units), from the median absolute
    deviation of their second differences (white noise of ``sigma`` gives ``sigma sqrt(6)``; the smooth rise and a
    few spikes barely move the median); 0 with fewer than 3 readings."""
    second = np.diff(np.asarray(values, dtype=np.float64), 2)
    return _mad_sigma(second) / math.sqrt(6.0) if second.size else 0.0


def _mad_sigma(x: np.ndarray) -> float:
    """The standard deviation of Gaussian values ``x`` from their median absolute deviation (outliers do not count)."""
    return MAD_TO_SIGMA * float(np.median(np.abs(x - np.median(x))))


#: The first rise of a dip, as shares of its range: the readings between these show where contact began.
FIRST_RISE = (0.02, 0.2)


def rest_readings(o: OrientationScan) -> np.ndarray:
    """Indices ``(m,)`` of a dip's readings at rest level, before the object touched the water (at least one).

    The object is in once the level has risen the first share of :data:`FIRST_RISE` of the dip's range, but
    the readings just before hold its first touch: near contact a smooth surface's wetted volume grows as the
    square of the depth, so the square root of the rise is a line in the stage position (mm), and its zero,
    fitted to the readings up to the second share, is where contact began. Readings from one stage step
    before it on are dropped. A flat face, whose volume grows linearly, puts that zero early, so more are
    dropped; a vertex, growing as the cube, puts it late and leaves a tenth of the first share. Without a
    usable line only the last reading below the first share is dropped.
    """
    spread = max(float(np.ptp(o.values)), 1e-300)
    onset, risen = (onset_index(o.values, share * spread) for share in FIRST_RISE)
    before = np.arange(onset)
    kept = max(1, onset - 1)
    stage, first = o.stage_mm[onset:risen], o.values[onset:risen] - o.values[0]
    if first.size >= 2 and np.ptp(stage) > 0:
        slope, intercept = np.polyfit(stage, np.sqrt(np.maximum(first, 0.0)), 1)
        if slope > 0:
            step = float(np.median(np.diff(o.stage_mm)))
            kept = min(kept, max(1, int(np.sum(o.stage_mm[before] < -intercept / slope - step))))
    return before[:kept]


def _robust_slope(t: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope, refitted without readings 4 MADs off the line (spikes); the last slope that had
    two distinct times to stand on (NaN if the first fit had none)."""
    slope = float("nan")
    for _ in range(3):
        centred = t - t.mean()  # clock times (epoch seconds) would make the fit ill-conditioned
        spread = float(np.dot(centred, centred))
        if not spread > 0:
            break
        slope = float(np.dot(centred, y - y.mean()) / spread)
        r = y - y.mean() - slope * centred
        mad = _mad_sigma(r) + 1e-12
        keep = np.abs(r) <= 4 * mad
        if keep.all() or keep.sum() < 3:
            break
        t, y = t[keep], y[keep]
    return slope


def dip_moments(raw: RawScan, geometry: RigGeometry, section_sd: float | None = None) -> DipMoments:
    """The moment sums of every complete dip, with drift and lag of ``geometry`` undone (its outlier readings
    repaired with the drift taken out,
    :func:`~dipnet.preprocessing.preprocess.repair_without_drift`).

    A balance's readings (g) become the water line's rise over the tank's section: ``geometry``'s
    ``cross_section_mm2`` when it holds one, else the scan's nominal one; ``section_sd`` is how well that section
    is known (relative standard deviation; ``None``: :data:`BALANCE_SECTION_SD`, the calibrated range +-20 %; 0:
    exactly), which the bootstrap draws (:attr:`DipMoments.rise_scale_sd`). A level sensor reads the rise itself:
    ``section_sd`` plays no part.

    Raises ``ValueError`` for a 2D scan (its dips are angles in a plane: no rig to calibrate), or naming a dip whose
    level never rises or that has no rig angles.
    """
    if raw.header.ndim != 3:
        raise ValueError(f"the scan{'' if raw.path is None else ' ' + str(raw.path)} is {raw.header.ndim}D (its "
                         "header's ndim): its dips are angles in a plane, with no tilt and spin, so no rig geometry "
                         "can be calibrated from it; calibrate the rig on a 3D scan")
    applied = scan_geometry(raw.header)
    repaired, _ = repair_without_drift(raw, geometry.level_drift_mm_per_s)
    nominal = geometry.area(float(raw.header.tank_cross_section_mm2 or 1.0))
    rows, gains = [], []
    for o in complete_dips(repaired):
        if o.tilt_deg is None or o.spin_deg is None:
            raise ValueError(f"dip {o.k} has no rig angles: the rig geometry cannot be calibrated from it")
        order = np.argsort(o.stage_mm, kind="stable")
        stage = o.stage_mm[order]
        to_level = 1.0 if raw.header.quantity == "level_mm" else 1.0 / raw.header.density_g_per_mm3 / nominal
        if raw.header.quantity == "level_mm":
            values = geometry.invert_levels(o.values, o.time_s)[order]
        else:  # a balance: displaced volume over the nominal section, in mm of level
            values = o.values[order] * to_level
        rise = _rise(values, (raw.header.resolution or 0.0) * to_level)
        w = np.diff(rise)
        total = float(w.sum())
        if not total > 0:
            raise ValueError(f"dip {o.k}: the level never rises, it cannot place the object")
        s_mid, r_mid = 0.5 * (stage[1:] + stage[:-1]), 0.5 * (rise[1:] + rise[:-1])
        ds, dr = np.diff(stage), np.diff(rise)  # Sheppard's correction: grouping in steps adds step^2 / 12
        recorded = float(o.meta.get("t_start_mm", raw.header.t_start_mm or 0.0))
        gains.append(_level_gain(ds, dr))
        rows.append((o.tilt_deg, o.spin_deg, recorded - float(applied.height_shift([o.tilt_deg])[0]), rise[-1],
                     w @ s_mid / total, w @ r_mid / total, w @ (s_mid**2 - ds**2 / 12) / total,
                     w @ (s_mid * r_mid - ds * dr / 12) / total, w @ (r_mid**2 - dr**2 / 12) / total, o.k))
    if len(rows) < 3:
        raise ValueError(f"calibration needs at least 3 complete dips, the scan has {len(rows)}")
    cols = list(zip(*rows))
    balance_sd = BALANCE_SECTION_SD if section_sd is None else float(section_sd)
    return DipMoments(*(np.asarray(c, dtype=np.float64) for c in cols[:9]), k=list(cols[9]),
                      rise_scale_sd=0.0 if raw.header.quantity == "level_mm" else balance_sd,
                      level_gain=float(np.median(gains)))


#: A water line rising more than this per mm of stage (an object whose section exceeds a third of the tank's) is
#: warned about: the moments' sums over a step assume it moves little within one. A 30 mm ball (1.5 mm steps) in
#: tanks of 6,000 and 4,000 mm^2 (gains 0.9 and 2.4): the offset 13.6 standard errors off, the step scale 1.009
#: [1.0068, 1.0113] for 1; at 20,000 mm^2 (gain 0.16) every interval held.
SNUG_LEVEL_GAIN = 0.5


def _level_gain(ds: np.ndarray, dr: np.ndarray) -> float:
    """The steepest rise of the water line per mm of stage over three consecutive steps (``ds``, ``dr``: the
    steps of stage and rise, mm); 0 without three steps."""
    if len(ds) < 3:
        return 0.0
    window = np.ones(3)
    travel = np.convolve(ds, window, mode="valid")
    return float(np.max(np.convolve(dr, window, mode="valid") / np.maximum(travel, 1e-12)))


def _rise(values: np.ndarray, quantum: float = 0.0) -> np.ndarray:
    """The level rise ``(n,)`` mm of one dip: monotone, exactly 0 before contact and flat once under water.

    Noise in the flat parts would add small rises far from the object's centre and inflate its
    second moment (a 0.3 % step-scale bias on a 30 mm ball at 30 dB), so the rise is cut to the
    span where it leaves the rest level and reaches the final one by more than 3 noise sigmas
    (the noise from the readings' own second differences, MAD, and at least the rounding's: ``quantum / sqrt(12)``
    with ``quantum`` the readings' resolution in mm of level, as the readings' repair takes it). Readings rounded
    more coarsely than their noise have second differences mostly 0: a 0.01 g balance under a 2,000 mm^3 hammer
    read a noise of 1e-16 g, the flicker of its last level passed for rise, and a self-calibration's tilt zero came
    out 0.43 deg off with an interval of +-0.15 deg (pivot and offset 2-3 half-widths off too).
    """
    spread = max(float(np.ptp(values)), 1e-300)
    noise = math.hypot(reading_sigma(values), quantum / math.sqrt(12.0))
    tol = max(3.0 * noise, 1e-9 * spread)
    onset = onset_index(values, tol)
    level = values - values[: max(1, onset - 1)].mean()
    rise = scipy.optimize.isotonic_regression(level).x
    final = float(rise[-max(1, min(3, len(rise) // 10)):].mean())
    inside = (rise > tol) & (rise < final - tol)
    if inside.any():
        first, last = np.flatnonzero(inside)[[0, -1]]
        rise[: max(first - 1, 0)] = 0.0  # one reading either side of the span keeps its partial rise
        final = _final_level(level[last + 2:], final)
        rise[last + 2:] = final
    return np.clip(rise, 0.0, final)


def _final_level(plateau: np.ndarray, fallback: float) -> float:
    """The level ``plateau`` ``(n,)`` mm (the readings once the object is under water, rest level removed) holds:
    their mean, ``fallback`` when there are none.

    Not the isotonic fit's last value: that is the largest of the tail's running means, high by about half a
    noise sigma (0.46 sigma over 160 dips of a 30 mm ball at 30 dB), which put a reference's cross-section and step
    scale about one standard error low on a 16-dip plan."""
    return float(plateau.mean()) if plateau.size else fallback


# ------------------------------------------------------------------------------------ the model
#: A reference object's centroid closer than this (mm) to the spin axis is taken as on it (:meth:`KnownObject.radial`).
ON_AXIS_MM = 5.0


def radial_direction(centroid: np.ndarray) -> np.ndarray | None:
    """The unit horizontal direction ``(3,)`` from the spin axis to ``centroid`` ``(3,)`` mm, or ``None``
    within :data:`ON_AXIS_MM` of the axis."""
    horizontal = np.array([centroid[0], centroid[1], 0.0])
    distance = float(np.linalg.norm(horizontal))
    return horizontal / distance if distance > ON_AXIS_MM else None


@dataclass
class KnownObject:
    """A reference object's moments: centroid ``(3,)`` mm, covariance ``(3, 3)`` mm^2, volume mm^3."""

    centroid: np.ndarray
    covariance: np.ndarray
    volume: float

    def radial(self) -> np.ndarray | None:
        """The unit horizontal direction ``(3,)`` from the spin axis to the centroid, or ``None`` within
        :data:`ON_AXIS_MM` of the axis.

        The moment stage fits the centroid's distance along it (a nuisance): a tilt-zero error moves the dips'
        heights by ``delta (c . d theta / d tilt)``, which varies with the tilt as ``cos r``, a distance error as
        ``sin r``, so the tilt zero of a reference off the axis does not depend on how well its distance is
        known. Its direction stays fixed: a turn about the spin axis is the spin zero."""
        return radial_direction(self.centroid)

    @classmethod
    def ball(cls, radius_mm: float, centre=(0.0, 0.0, 0.0)) -> "KnownObject":
        r = float(radius_mm)
        return cls(np.asarray(centre, dtype=np.float64), np.eye(3) * r * r / 5.0, 4.0 / 3.0 * np.pi * r**3)


@dataclass
class MomentFit:
    """The moment stage's estimate.

    Attributes:
        values: parameter -> estimate (RigGeometry units; ``t0_mm`` the common start-height offset).
        free: the parameters that were fitted.
        residual_rms: ``(first, second)`` RMS of the moment residuals (mm, mm^2).
        centroid, covariance: the object's fitted (or known) moments.
        start: the configured values the search is centred on.
        intervals: parameter -> (5th, 95th) bootstrap percentile.
        bootstrap_sd: parameter -> bootstrap standard deviation.
        profile_rise: nonlinear parameter -> the least rise of the whitened misfit (chi^2 units)
            when it is moved by its tolerance and the others refitted: below 2.71 (the 90%
            profile-likelihood level) the dips cannot pin it to its tolerance.
    """

    values: dict[str, float]
    free: tuple[str, ...]
    residual_rms: tuple[float, float]
    centroid: np.ndarray
    covariance: np.ndarray
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    bootstrap_sd: dict[str, float] = field(default_factory=dict)
    profile_rise: dict[str, float] = field(default_factory=dict)
    correlations: dict[str, dict[str, float]] = field(default_factory=dict)
    start: dict[str, float] = field(default_factory=dict)

    def at_search_edge(self, name: str) -> bool:
        """Whether the nonlinear parameter ``name``'s estimate reached the edge of its search range."""
        return name in SEARCH and abs(self.values[name] - self.start[name]) >= 2 * SEARCH[name][0] - 1e-6

    def undetermined(self, kind: str) -> dict[str, str]:
        """Free parameter -> why the dips do not determine it to its :data:`TOLERANCE` (``kind``:
        ``"self"`` or ``"reference"``, for the named degeneracies of :data:`GAUGE_REASONS`)."""
        out = {}
        for name in self.free:
            if self.at_search_edge(name):
                out[name] = (f"the estimate reached the edge of the search range ({self.start[name]:g} "
                             f"+- {2 * SEARCH[name][0]:g}): the rig is outside the calibrated range, or the dips are "
                             "not of one rigid object")
                continue
            rise = self.profile_rise.get(name)
            low, high = self.intervals.get(name, (self.values[name], self.values[name]))
            half = 0.5 * (high - low)
            if rise is not None and rise < 2.71:
                off_axis = kind == "reference" and radial_direction(self.centroid) is not None
                reason = GAUGE_REASONS.get(("off_axis", name)) if off_axis else None
                out[name] = (reason or GAUGE_REASONS.get((kind, name), "the dips barely depend on it")) + \
                    f" (moving it by {TOLERANCE[name]:g} raises the misfit by {rise:.2g}, less than 2.71)"
            elif half > TOLERANCE[name]:
                out[name] = f"its 90% interval (bootstrap over dips) is +-{half:.3g}, wider than {TOLERANCE[name]:g}"
        return out


def _quadratic_design(d: np.ndarray) -> np.ndarray:
    """``(..., K, 6)`` columns of ``theta^T S theta`` for the 6 entries of a symmetric ``S`` (xx, yy, zz, xy, xz,
    yz), from directions ``d`` ``(..., K, 3)``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([x**2, y**2, z**2, 2 * x * y, 2 * x * z, 2 * y * z], axis=-1)


def rig_directions(tilt_deg: np.ndarray, spin_deg: np.ndarray) -> np.ndarray:
    """:func:`~dipnet.core.orientations.rig_to_direction`'s unit directions ``(..., 3)`` for numpy arrays of rig
    angles (degrees) of broadcastable shapes ``(...)``, without its tensor conversions' overhead in the fits' inner
    loops.

    The sines and cosines are torch's, as there: for ``(K,)`` angles the directions are the same to the last bit
    (numpy's differ by an ulp in some), so a fit's rounding, and where a flat misfit leaves it, is the same too.
    """
    t, s = (torch.from_numpy(np.radians(a, dtype=np.float64)) for a in np.broadcast_arrays(tilt_deg, spin_deg))
    sin_t = t.sin().numpy()
    return np.stack([sin_t * s.cos().numpy(), -sin_t * s.sin().numpy(), t.cos().numpy()], axis=-1)


def _stack_columns(columns: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """The design ``(*shape, J)`` of ``J`` columns broadcastable to ``shape`` (``(P, K)``: points, dips)."""
    return np.stack([np.broadcast_to(c, shape) for c in columns], axis=-1)


def _projection_residual(design: np.ndarray, b: np.ndarray) -> np.ndarray:
    """What ``b`` ``(..., N)`` leaves after its least-squares fit by the columns of ``design`` ``(..., N, J)``, for a
    stack of systems at once: ``np.linalg.lstsq``'s residual (its ``rcond``: singular values below ``eps max(N, J)``
    of the largest drop out), to rounding."""
    u, s, _ = np.linalg.svd(design, full_matrices=False)
    u = u * (s > np.finfo(np.float64).eps * max(design.shape[-2:]) * s[..., :1])[..., None, :]
    b = np.broadcast_to(b, design.shape[:-1])
    return b - np.einsum("...nj,...j->...n", u, np.einsum("...nj,...n->...j", u, b))


class MomentModel:
    """Residuals of the two range conditions for trial values of the nonlinear parameters.

    Args:
        moments: the scan's :class:`DipMoments`.
        known: a reference object (its moments fixed), or ``None`` (self-calibration: the
            centroid and covariance are free).
        fixed: values of parameters that are not fitted (defaults: the ideal rig, ``t0_mm`` 0).
        linear_free: which of ``pivot_mm``, ``tilt_axis_offset_mm``, ``t0_mm`` are fitted.
        priors: a reference object's nuisances known to a tolerance, fitted with a Gaussian prior:
            name (:data:`NUISANCES`) -> standard deviation (mm) about the assumed value (``fixed["t0_mm"]``;
            ``known``'s centroid for the shifts). Their prior residuals ``departure / sd`` join the first
            condition's whitened residuals (:attr:`weights`), so the dips decide what they determine (a ball
            off the axis shows its start height) and the prior the rest.
    """

    def __init__(self, moments: DipMoments, known: KnownObject | None, fixed: dict[str, float],
                 linear_free: tuple[str, ...], priors: dict[str, float] | None = None) -> None:
        self.m, self.known, self.fixed, self.linear_free = moments, known, dict(fixed), linear_free
        self.radial = None if known is None else known.radial()  # its distance from the spin axis: fitted
        self.priors = {n: float(sd) for n, sd in (priors or {}).items() if sd > 0} if known is not None else {}
        unknown = set(self.priors) - set(NUISANCES)
        if unknown or set(self.priors) & set(linear_free):
            raise ValueError(f"priors are for the nuisances {list(NUISANCES)} not fitted otherwise, "
                             f"got {sorted(self.priors)}")
        self.weights = (1.0, 1.0)
        self.prior_residual = np.zeros(0)  # the priors' residuals at the last solve, in the units of r1

    def _conditions(self, p: dict[str, float | np.ndarray]) -> tuple[np.ndarray, np.ndarray, list[np.ndarray],
                                                                     np.ndarray]:
        """The range conditions' parts at the parameter values ``p`` (floats, or ``(P, 1)`` arrays for ``P`` points):
        ``(theta (..., K, 3), target (..., K), columns, var (..., K))``, ``columns`` the linear unknowns' ``(..., K)``
        (``linear_free``, the priors', a known object's distance from the spin axis): ``target + sum_j x_j column_j``
        is the first condition's residual (its ``c . theta`` too among the unknowns for an unknown object)."""
        tilt = self.m.tilt_deg + p["tilt_zero_deg"]
        r = np.radians(tilt)
        theta = rig_directions(tilt, self.m.spin_deg + p["spin_zero_deg"])
        mean, var = self.m.centroid_and_variance(p["step_scale"])
        columns = {"pivot_mm": np.cos(r) - 1.0, "tilt_axis_offset_mm": np.sin(r), "t0_mm": np.ones_like(r)}
        target = self.m.t_recorded + mean + sum(p[n] * columns[n] for n in columns if n not in self.linear_free)
        lin = [columns[n] for n in self.linear_free]
        if self.known is None:  # target + sum_j x_j column_j = c . theta
            return theta, target, lin + [-theta[..., i] for i in range(3)], var
        nuisance = {"t0_mm": columns["t0_mm"], **{f"shift_{a}_mm": -theta[..., i] for i, a in enumerate("xyz")}}
        lin = lin + [nuisance[n] for n in self.priors]  # each fitted as its departure from its assumed value
        if self.radial is not None:  # a nuisance column: the distance from the spin axis
            lin = lin + [-theta @ self.radial]
        return theta, target - theta @ self.known.centroid, lin, var

    def _ridge(self, n_columns: int) -> np.ndarray:
        """The priors' rows ``(len(priors), n_columns)``: ``(x - mean) / sd`` in the whitened units of r1."""
        ridge = np.zeros((len(self.priors), n_columns))
        for row, name in enumerate(self.priors):
            ridge[row, len(self.linear_free) + row] = self.weights[0] / self.priors[name]
        return ridge

    def _fit(self, nonlinear: dict[str, float]) -> tuple[dict[str, float], np.ndarray, np.ndarray, np.ndarray,
                                                         np.ndarray]:
        """``(p, r1 (K,), r2 (K,), x, s6)`` at ``nonlinear``: all parameter values ``p``, the residuals, the linear
        unknowns ``x`` (``_conditions``' columns) and an unknown object's covariance entries ``s6`` (6,) (else
        empty); :attr:`prior_residual` too."""
        p = {**self.fixed, **nonlinear}
        theta, target, lin, var = self._conditions(p)
        if self.known is None:
            design = np.column_stack(lin)
            x = np.linalg.lstsq(design, -target, rcond=None)[0]
            quad = _quadratic_design(theta)
            s6 = np.linalg.lstsq(quad, var, rcond=None)[0]
            return p, target + design @ x, var - quad @ s6, x, s6
        if lin:
            design = np.column_stack(lin)
            ridge = self._ridge(design.shape[1])
            rhs = np.concatenate([target, np.zeros(len(ridge))])
            x = np.linalg.lstsq(np.vstack([design, ridge]), -rhs, rcond=None)[0]
            r1 = target + design @ x
            self.prior_residual = ridge @ x
        else:
            x, r1 = np.zeros(0), target
        return p, r1, var - np.einsum("ki,ij,kj->k", theta, self.known.covariance, theta), x, np.zeros(0)

    def solve(self, nonlinear: dict[str, float]) -> tuple[np.ndarray, np.ndarray, dict[str, float], np.ndarray,
                                                          np.ndarray]:
        """``(r1 (K,), r2 (K,), linear values, centroid (3,), covariance (3, 3))`` at ``nonlinear``."""
        p, r1, r2, x, s6 = self._fit(nonlinear)
        if self.known is None:
            values = dict(zip(self.linear_free, x[: len(self.linear_free)]))
            cov = np.array([[s6[0], s6[3], s6[4]], [s6[3], s6[1], s6[5]], [s6[4], s6[5], s6[2]]])
            return r1, r2, values, x[len(self.linear_free):], cov
        values = dict(zip(list(self.linear_free) + list(self.priors), x))
        if "t0_mm" in self.priors:
            values["t0_mm"] += p["t0_mm"]
        centroid = self.known.centroid + np.array([values.get(f"shift_{a}_mm", 0.0) for a in "xyz"])
        if self.radial is not None:
            centroid = centroid + x[-1] * self.radial
        return r1, r2, values, centroid, self.known.covariance

    def misfits(self, points: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``(r1 (P, K), r2 (P, K))`` at ``P`` points of the nonlinear parameters at once (name -> ``(P,)``): what
        :meth:`solve` gives point by point, to rounding."""
        p = {**self.fixed, **{n: np.asarray(v, dtype=np.float64)[:, None] for n, v in points.items()}}
        theta, target, lin, var = self._conditions(p)
        shape = np.broadcast_shapes(theta.shape[:-1], target.shape, var.shape)
        theta = np.broadcast_to(theta, (*shape, 3))
        if self.known is None:
            design = _stack_columns(lin, shape)
            return _projection_residual(design, target), _projection_residual(_quadratic_design(theta), var)
        r2 = var - np.einsum("...ki,ij,...kj->...k", theta, self.known.covariance, theta)
        if not lin:
            return np.broadcast_to(target, shape), r2
        design = _stack_columns(lin, shape)
        ridge = np.broadcast_to(self._ridge(design.shape[-1]), (*shape[:-1], len(self.priors), design.shape[-1]))
        rhs = np.concatenate([np.broadcast_to(target, shape), np.zeros((*shape[:-1], len(self.priors)))], axis=-1)
        return _projection_residual(np.concatenate([design, ridge], axis=-2), rhs)[..., :shape[-1]], r2

    def residual(self, nonlinear: dict[str, float]) -> np.ndarray:
        """The whitened residuals ``(2 K + len(priors),)`` at ``nonlinear``: both conditions', the priors'."""
        _, r1, r2, *_ = self._fit(nonlinear)
        return np.concatenate([r1 / self.weights[0], r2 / self.weights[1], self.prior_residual / self.weights[0]])


def spare_conditions(n_dips: int, free: tuple[str, ...], known: KnownObject | None) -> int:
    """The moment conditions of ``n_dips`` dips (two each: the volume's mean height and spread) less the
    unknowns: the ``free`` parameters and, for an unknown object (``known`` ``None``), its centroid (3) and
    covariance (6); for a reference object off the spin axis its distance from the axis (1)."""
    unknowns = len(free) + (9 if known is None else int(known.radial() is not None))
    return 2 * int(n_dips) - unknowns


#: A free pivot, offset or start height whose first-moment column lies within this (relative) of the span of the
#: other unknowns' columns is confounded with them (:func:`confounded_heights`).
CONFOUNDED = 1e-6


def _nuisance_priors(known: KnownObject | None, free: tuple[str, ...], t0_sd_mm: float,
                     position_sd_mm: float) -> dict[str, float]:
    """The priors (name -> standard deviation, mm) :func:`fit_moments` fits a reference object's nuisances with: the
    common start height's (``t0_sd_mm`` with :data:`START_MODEL_SD_MM` in quadrature) unless ``t0_mm`` is free, and
    the object's position's along x, y, z; none for an unknown object (``known`` ``None``)."""
    if known is None:
        return {}
    t0_sd_mm = float(np.hypot(t0_sd_mm, START_MODEL_SD_MM))
    return {n: sd for n, sd in (("t0_mm", t0_sd_mm), ("shift_x_mm", position_sd_mm), ("shift_y_mm", position_sd_mm),
                                ("shift_z_mm", position_sd_mm)) if n not in free}


def confounded_heights(moments: DipMoments, free: tuple[str, ...], *, known: KnownObject | None = None,
                       fixed: dict[str, float] | None = None, t0_sd_mm: float = 0.0,
                       position_sd_mm: float = 0.0) -> dict[str, str]:
    """Free pivot, tilt-axis offset or start height (``free``'s linear parameters) -> why the dips' first moments
    cannot tell it from the other unknowns, for those whose column (``cos r - 1``, ``sin r``, 1 over the dips' tilts
    ``r``) lies in the span of the others' (with the priors' rows of :func:`fit_moments`: ``known``, ``t0_sd_mm``,
    ``position_sd_mm``) to :data:`CONFOUNDED`.

    Such a parameter is not determined whatever the noise: the least-squares fit takes one split of the heights
    among the confounded unknowns, and every bootstrap refit of the same tilts takes the same, so its interval is
    tight and meaningless (the audit: a ball dipped at one tilt of 30 deg gave a pivot of 7.6 mm, interval
    [7.2, 7.9], for a true 30; an unknown object at tilts 0 and 40 deg, 10.3 mm, [9.4, 12.0]). One or two distinct
    tilts confound the pivot with the offset (and an unknown object's height); one spin confounds the offset with an
    unknown object's sideways position.
    """
    fixed = {"pivot_mm": 0.0, "tilt_axis_offset_mm": 0.0, "tilt_zero_deg": 0.0, "spin_zero_deg": 0.0,
             "step_scale": 1.0, "t0_mm": 0.0, **(fixed or {})}
    linear = tuple(p for p in ("pivot_mm", "tilt_axis_offset_mm", "t0_mm") if p in free)
    model = MomentModel(moments, known, fixed, linear, _nuisance_priors(known, free, t0_sd_mm, position_sd_mm))
    _, _, columns, _ = model._conditions(fixed)
    design = np.column_stack([np.broadcast_to(c, moments.tilt_deg.shape) for c in columns])
    design = np.vstack([design, model._ridge(design.shape[1])])
    tilts = np.unique(np.round(moments.tilt_deg, 3))
    spins = np.unique(np.round(np.mod(moments.spin_deg, 360.0), 3))
    out = {}
    for j, name in enumerate(linear):
        column, others = design[:, j], np.delete(design, j, axis=1)
        left = column - others @ np.linalg.lstsq(others, column, rcond=None)[0] if others.shape[1] else column
        norm = float(np.linalg.norm(column))
        if not norm > 0 or float(np.linalg.norm(left)) <= CONFOUNDED * norm:
            out[name] = (f"the dips' first moments cannot tell it from the other unknowns (the pivot, the tilt-axis "
                         f"offset, the start height"
                         f"{', the object' + chr(39) + 's position' if known is None else ''}): "
                         f"{len(tilts)} distinct tilt(s) ({', '.join(f'{t:g}' for t in tilts[:6])}"
                         f"{', ...' if len(tilts) > 6 else ''} deg) and {len(spins)} spin(s) leave any split of the "
                         "heights among them as good, and a bootstrap over the same tilts repeats one; dip at three or "
                         "more tilts spread over 0-60 deg (and two or more spins)")
    return out


def fit_moments(moments: DipMoments, free: tuple[str, ...], *, known: KnownObject | None = None,
                fixed: dict[str, float] | None = None, bootstrap: int = BOOTSTRAP, seed: int = 0,
                t0_sd_mm: float = 0.0, position_sd_mm: float = 0.0) -> MomentFit:
    """Fit the free parameters (:data:`MOMENT_PARAMETERS`) to the dips' moments.

    The nonlinear ones (tilt zero, spin zero, step scale) are searched on the :data:`SEARCH`
    grid around their fixed value, then refined with ``scipy.optimize.least_squares`` inside
    that range; the linear ones are solved in closed form at every trial. ``bootstrap`` refits
    over dips drawn with replacement give the 90% intervals (0: none).

    A reference object's nuisances known to a tolerance are fitted with a Gaussian prior (:class:`MomentModel`'s
    ``priors``), after a grid search that holds them at their assumed values: ``t0_sd_mm``, the common start
    height's standard deviation (mm: the stage's zero against the water line, the shift a sensor lag gives every
    dip), when ``t0_mm`` is not free; ``position_sd_mm``, its centre's along each axis of the object frame (mm:
    its mounting; mounted higher, it moves every dip's height as ``cos r``, a longer pivot plus a start height;
    sideways, it turns against the spin zero). The dips decide what they show (a ball off the spin axis shows
    its start height, so its tilt zero and offset do not hang on it) and the priors the rest (a centred ball's
    tilt zero). Every bootstrap refit also draws the assumed values from the priors (a randomised-prior
    bootstrap: for a linear model with Gaussian errors its draws follow the posterior).
    """
    fixed = {"pivot_mm": 0.0, "tilt_axis_offset_mm": 0.0, "tilt_zero_deg": 0.0, "spin_zero_deg": 0.0,
             "step_scale": 1.0, "t0_mm": 0.0, **(fixed or {})}
    unknown = [p for p in free if p not in MOMENT_PARAMETERS]
    if unknown:
        raise ValueError(f"the moment stage cannot fit {unknown}; it fits {list(MOMENT_PARAMETERS)}")
    linear = tuple(p for p in ("pivot_mm", "tilt_axis_offset_mm", "t0_mm") if p in free)
    nonlinear = tuple(p for p in SEARCH if p in free)
    priors = _nuisance_priors(known, tuple(free), t0_sd_mm, position_sd_mm)
    t0_sd_mm = float(np.hypot(t0_sd_mm, START_MODEL_SD_MM)) if known is not None else t0_sd_mm
    coarse = MomentModel(moments, known, fixed, linear)  # the nuisances at their assumed values
    start = _grid_search(coarse, nonlinear, fixed)
    model = MomentModel(moments, known, fixed, linear, priors)
    model.weights = _group_scales(coarse, start)  # each condition in units of its own misfit
    best = _refine(model, nonlinear, start, fixed)
    r1, r2, lin, centroid, cov = model.solve(best)
    fit = MomentFit(values={**fixed, **best, **lin}, free=tuple(free), start=dict(fixed),
                    residual_rms=(float(np.sqrt(np.mean(r1**2))), float(np.sqrt(np.mean(r2**2)))),
                    centroid=centroid, covariance=cov)
    cost = float(np.sum(model.residual(best) ** 2))
    for name in nonlinear:
        others = tuple(n for n in nonlinear if n != name)
        rises = []
        for sign in (-1.0, 1.0):
            moved = {**fixed, **best, name: best[name] + sign * TOLERANCE[name]}
            trial = MomentModel(moments, known, moved, linear, priors)
            trial.weights = model.weights
            refit = _refine(trial, others, best, moved)
            rises.append(float(np.sum(trial.residual({**refit, name: moved[name]}) ** 2)) - cost)
        fit.profile_rise[name] = min(rises)
    if bootstrap:
        rng = np.random.default_rng(seed)
        draws = {p: [] for p in free}
        for _ in range(int(bootstrap)):
            drawn = dict(fixed)
            if t0_sd_mm > 0 and "t0_mm" not in free:
                drawn["t0_mm"] = fixed["t0_mm"] + rng.normal(0.0, t0_sd_mm)
            placed = known
            if known is not None and position_sd_mm > 0:
                placed = replace(known, centroid=known.centroid + rng.normal(0.0, position_sd_mm, 3))
            drawn_moments = moments.take(rng.integers(0, len(moments.k), len(moments.k)))
            if moments.rise_scale_sd > 0:  # no draw otherwise: a level scan's bootstrap is unchanged
                drawn_moments = drawn_moments.rise_scaled(max(1.0 + rng.normal(0.0, moments.rise_scale_sd), 0.1))
            sub = MomentModel(drawn_moments, placed, drawn, linear, priors)
            sub.weights = model.weights
            b = _refine(sub, nonlinear, best, drawn)
            values = {**b, **sub.solve(b)[2]}
            for p in free:
                draws[p].append(values[p])
        for p, xs in draws.items():
            xs = np.asarray(xs)
            fit.bootstrap_sd[p] = float(xs.std(ddof=1))
            fit.intervals[p] = (float(np.percentile(xs, 5)), float(np.percentile(xs, 95)))
        if len(free) > 1:
            with np.errstate(invalid="ignore", divide="ignore"):  # a parameter at its bound does not vary
                corr = np.nan_to_num(np.corrcoef(np.asarray([draws[p] for p in free])))
            fit.correlations = {p: {q: float(corr[i, j]) for j, q in enumerate(free) if j != i}
                                for i, p in enumerate(free)}
    return fit


#: Grid points whose batched misfit (:meth:`MomentModel.misfits`) is within this of the least are compared by
#: :meth:`MomentModel.solve`'s, so that rounding never picks another point than a point-by-point search would.
TIE = 1e-6


def _grid_search(model: MomentModel, names: tuple[str, ...], fixed: dict[str, float]) -> dict[str, float]:
    """The grid point of the nonlinear parameters with the smallest (scale-free) moment misfit (the first of equal
    ones in the grid's order). All points are evaluated at once; those within :data:`TIE` of the least again one
    by one."""
    if not names:
        return {}
    axes = [fixed[n] + np.arange(-SEARCH[n][0], SEARCH[n][0] + 1e-9, SEARCH[n][1]) for n in names]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(names))
    costs = _scale_free_misfit(*model.misfits(dict(zip(names, points.T))))
    near = np.flatnonzero(costs <= np.nanmin(costs) + TIE)
    exact = [_scale_free_misfit(*model.solve(dict(zip(names, points[i])))[:2]) for i in near]
    return {n: float(v) for n, v in zip(names, points[near[np.nanargmin(exact)]])}


def _scale_free_misfit(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """``log mean r1^2 + log mean r2^2`` over the dips (the last axis of ``r1``, ``r2`` ``(..., K)``): invariant to
    each condition's scale."""
    return np.log(np.mean(r1**2, axis=-1) + 1e-30) + np.log(np.mean(r2**2, axis=-1) + 1e-30)


#: The least misfit scale of a moment condition, relative to the RMS of the condition's own values: noise-free dips
#: fit to rounding (1e-13 of them), and in units of that every rounding difference looked like data (a centred ball,
#: noise-free: its tilt zero, which no dip of it shows, "determined" at -6.000 +- 0.02 deg for a true 0). Far below
#: any measured noise (a 1 um reading step on 50 mm heights is 2e-5 of them).
ROUNDING_SCALE = 1e-9


def _group_scales(model: MomentModel, at: dict[str, float]) -> tuple[float, float]:
    """Each condition's misfit scale at ``at``: its RMS residual, at least :data:`ROUNDING_SCALE` of the RMS of the
    condition's values (1 when both are 0)."""
    r1, r2, *_ = model.solve(at)
    _, target, _, var = model._conditions({**model.fixed, **at})
    return tuple(max(_rms(r), ROUNDING_SCALE * _rms(values)) or 1.0 for r, values in ((r1, target), (r2, var)))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _refine(model: MomentModel, names: tuple[str, ...], start: dict[str, float],
            fixed: dict[str, float]) -> dict[str, float]:
    if not names:
        return {}
    scale = np.array([SEARCH[n][1] for n in names])
    lo = np.array([fixed[n] - 2 * SEARCH[n][0] for n in names]) / scale
    hi = np.array([fixed[n] + 2 * SEARCH[n][0] for n in names]) / scale
    x0 = np.clip(np.array([start[n] for n in names]) / scale, lo + 1e-9, hi - 1e-9)
    result = scipy.optimize.least_squares(lambda x: model.residual(dict(zip(names, x * scale))), x0,
                                          bounds=(lo, hi), xtol=1e-10, ftol=1e-10, diff_step=1e-4)
    return {n: float(v) for n, v in zip(names, result.x * scale)}
