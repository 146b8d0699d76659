"""Calibration from a reference object of known shape: the moment stage, then the geometry fit."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Callable

import numpy as np
import scipy.ndimage
import scipy.optimize
import torch

from dipnet.calibration.model import (DEFAULT_REFERENCE, MODEL_FLOOR, CalibrationError, CalibrationReport, ProfileModel,
                                      State, _check_params, _warn_undetermined)
from dipnet.calibration.moments import (BALANCE_SECTION_SD, GAUGE_REASONS, MIN_SPARE_CONDITIONS, SNUG_LEVEL_GAIN,
                                       TOLERANCE, DipMoments, KnownObject, confounded_heights, dip_moments, fit_drift,
                                       fit_moments, reading_sigma, spare_conditions)
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.rawscan import RawScan
from dipnet.core.warn import log_and_warn
from dipnet.preprocessing.recorded import MAX_DROPPED_SHARE, truncated_orientations

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------- moment stage
SHAPE_MOTION = {
    "pivot_mm": "each mm moves a dip tilted by r by (1 - cos r) mm along it",
    "tilt_axis_offset_mm": "each mm moves a dip tilted by r by sin r mm along it",
    "tilt_zero_deg": "each degree tilts every dip direction by 1 deg: {arc:.2g} mm at the object's radius",
    "spin_zero_deg": "the shape turns about the spin axis by the spin zero's error: {arc:.2g} mm at the object's "
                     "radius per degree",
    "step_scale": "every length scales with it: 1 % moves the surface {pct:.2g} mm at the object's radius, "
                  "and the cross-section follows by 3 %",
    "cross_section_mm2": "every volume scales with it: 1 % changes the shape's size by about 0.33 %",
    "level_drift_mm_per_s": "an unremoved drift adds a rise that grows over the session",
}


def shape_motion(param: str, radius_mm: float) -> str:
    """How far an error of ``param`` moves the shape (:data:`SHAPE_MOTION`), at the object's radius ``radius_mm``;
    without that radius (NaN: the dips gave no fit of the object's moments) the motion is said without its size."""
    text = SHAPE_MOTION[param]
    if math.isfinite(radius_mm):
        return text.format(arc=np.radians(radius_mm), pct=0.01 * radius_mm)
    if "{" not in text:
        return text
    return (text.split(":")[0] + " (how far that moves the surface needs the object's size, which the dips' moments "
            "did not give)")


def _moment_stage(raw: RawScan, params, initial: RigGeometry, kind: str, known: KnownObject | None,
                  seed: int = 0, t0_sd_mm: float = 0.0, position_sd_mm: float = 0.0,
                  section_sd: float | None = None) -> tuple[State, CalibrationReport, DipMoments]:
    """:func:`_fit_moment_stage`, refused when the dips' heights ask for a tilt axis that turns other than
    commanded (:func:`_check_tilt_scale`), which the geometry model does not hold, and warned about when the
    object fills so much of the tank that the moment sums are biased (:data:`~dipnet.calibration.moments.
    SNUG_LEVEL_GAIN`)."""
    state, report, moments = _fit_moment_stage(raw, params, initial, kind, known, seed, t0_sd_mm, position_sd_mm,
                                               section_sd)
    estimated = tuple(p for p in GEOMETRY_MOMENTS if p in report.estimates and p not in report.undetermined)
    drifted = initial.with_values(level_drift_mm_per_s=state.geometry.level_drift_mm_per_s)

    def misfit_at(scan: RawScan) -> float:
        return _moment_misfit(scan, estimated, drifted, known, t0_sd_mm, position_sd_mm, section_sd)

    _check_tilt_scale(raw, misfit_at(raw), misfit_at)
    if moments.level_gain > SNUG_LEVEL_GAIN:
        message = (f"{kind} calibration: the water line rises up to {moments.level_gain:.2g} mm per mm of stage (the "
                   f"object fills about {moments.level_gain / (1.0 + moments.level_gain):.0%} of the tank's section), "
                   f"so it moves {1.0 + moments.level_gain:.2g} times the stage step between readings, which the "
                   "dips' moment sums take for an even slab: the estimates may be biased beyond their intervals. "
                   "Use a tank several times the object's section, or smaller stage steps")
        log_and_warn(log, message, stacklevel=3)
    return state, report, moments


#: How far (relative) the tilt axis's probes lie from the commanded angles, and the range the search for the scale
#: the dips ask for covers (true tilt over commanded).
TILT_PROBE = 0.03
TILT_SCALE_RANGE = (0.75, 1.33)
#: A tilt scale is named when it is this far from 1 and fits the dips' first moments this many times better.
TILT_SCALE_TOL = 0.01
TILT_SCALE_GAIN = 3.0


#: The rig parameters the moment stage fits (:func:`_fit_moment_stage`); its other unknowns are nuisances.
GEOMETRY_MOMENTS = ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale")


def _moment_misfit(raw: RawScan, free: tuple[str, ...], geometry: RigGeometry, known: KnownObject | None,
                   t0_sd_mm: float, position_sd_mm: float, section_sd: float | None) -> float:
    """The RMS misfit (mm) of ``raw``'s dips' first moments with ``free`` (the moment stage's estimated parameters)
    fitted together around ``geometry`` (its level drift taken out of the readings), the nuisances as in
    :func:`_fit_moment_stage`, without its bootstrap and held parameters: what :func:`_check_tilt_scale` compares
    between the commanded tilts and scaled ones, at a small share of a whole stage's cost (a test's two calibrations
    of a 60-dip ball spent 54 of their 62 s in the probes when each was a whole stage)."""
    fixed = {f: float(getattr(geometry, f)) for f in GEOMETRY_MOMENTS}
    fit = fit_moments(dip_moments(raw, geometry, section_sd), free, known=known, fixed=fixed, bootstrap=0,
                      t0_sd_mm=t0_sd_mm, position_sd_mm=position_sd_mm)
    return fit.residual_rms[0]


def _check_tilt_scale(raw: RawScan, misfit: float, misfit_at: Callable[[RawScan], float]) -> None:
    """Refuse a calibration whose dips' heights fit only with the tilt axis turning ``s`` times the commanded
    angle (its steps per degree off), which no geometry of the model holds: it would otherwise bend the pivot,
    offset and tilt zero to fit (a 30 mm ball with ``s = 1/1.12``: pivot 15.7 [14.3, 17.0] for 20, "determined";
    self-calibration 70 standard errors off; the bunny with that file IoU 0.87 against 0.95, ``consistent``).

    ``misfit``: the first moments' RMS misfit (mm) at the commanded tilts; ``misfit_at(scaled)``: the same for
    the scan with every commanded tilt scaled. Two probes at ``1 -+ TILT_PROBE`` cost two moment fits; only when
    one of them fits better is the scale searched. On a ball's 16 dips the misfit was 0.0003 mm at the right
    scale and 0.08 mm at 5 % off; on 80 dips of a bunny 0.0023 against 0.0124 at 12 % off."""
    if not math.isfinite(misfit) or not all(o.tilt_deg is not None for o in raw.orientations) or \
            not any(o.tilt_deg for o in raw.orientations):
        return

    def scaled_misfit(scale: float) -> float:
        return misfit_at(replace(raw, orientations=[replace(o, tilt_deg=o.tilt_deg * scale)
                                                    for o in raw.orientations]))

    if misfit <= min(scaled_misfit(1.0 - TILT_PROBE), scaled_misfit(1.0 + TILT_PROBE)):
        return
    best = scipy.optimize.minimize_scalar(scaled_misfit, bounds=TILT_SCALE_RANGE, method="bounded",
                                          options={"xatol": 2e-3})
    scale = float(best.x)
    if abs(scale - 1.0) > TILT_SCALE_TOL and TILT_SCALE_GAIN * float(best.fun) < misfit:
        raise CalibrationError(
            f"the dips' heights fit the rig only with the tilt axis turning {scale:.3f} times the commanded angle "
            f"(their first moments miss by {misfit:.3g} mm as commanded, {float(best.fun):.3g} mm so): its steps per "
            f"degree are {abs(scale - 1.0):.1%} too {'few' if scale < 1.0 else 'many'}, which no rig geometry "
            "holds. Check the tilt axis's travel by hand (command 90 deg and measure), fix its scale "
            "(rig.controller.axes.tilt.scale, or the board's steps per degree) and dip again")


def _fit_moment_stage(raw: RawScan, params, initial: RigGeometry, kind: str, known: KnownObject | None,
                      seed: int = 0, t0_sd_mm: float = 0.0, position_sd_mm: float = 0.0,
                      section_sd: float | None = None) -> tuple[State, CalibrationReport, DipMoments]:
    """Stage 1 (module docstring): the drift, then the heights and angles from the dips' moments.

    ``kind`` is ``"self"`` (unknown object: spin zero and step scale are gauges, never fitted) or
    ``"reference"`` (``known`` moments; ``t0_sd_mm`` and ``position_sd_mm``: how well the start height and the
    object's mounting are known, see :func:`fit_moments`). ``section_sd``: how well a balance's tank section is
    known (relative standard deviation, :func:`~dipnet.calibration.moments.dip_moments`). The parameters the dips do not
    pin to their tolerance are settled by :func:`_hold_undetermined`; the others are refitted around them, their
    intervals widened to the joint fit's. Returns the state (its ``t0_mm`` the reference object's fitted start height:
    for its profile check only, never part of the geometry), the report and the dips' moments (drift removed: their
    rises give a reference object's cross-section).
    """
    geometry = initial
    report = CalibrationReport(estimates={}, standard_errors={}, correlations={},
                               method=kind)
    timed = raw.header.metadata.get("format") != "authors_csv" and any(np.ptp(o.time_s) > 0 for o in raw.orientations)
    if "level_drift_mm_per_s" in params and not (timed and raw.header.quantity == "level_mm"):
        report.not_estimated["level_drift_mm_per_s"] = ("not estimated: the recording has no reading times (or no "
                                                        "level readings); the configured value is used")
    elif "level_drift_mm_per_s" in params:
        drift, (low, high) = fit_drift(raw)
        _record(report, "level_drift_mm_per_s", drift, (low, high), (high - low) / 3.29,
                MODEL_FLOOR[kind]["level_drift_mm_per_s"])
        low, high = report.intervals["level_drift_mm_per_s"]
        if (high - low) / 2 > TOLERANCE["level_drift_mm_per_s"]:
            report.undetermined["level_drift_mm_per_s"] = (f"its 90% interval (bootstrap over dips) is "
                                                           f"+-{(high - low) / 2:.2g} mm/s, wider than "
                                                           f"{TOLERANCE['level_drift_mm_per_s']:g}")
            del report.intervals["level_drift_mm_per_s"]
        else:
            geometry = geometry.with_values(level_drift_mm_per_s=drift)
    moments = dip_moments(raw, geometry, section_sd)
    if kind == "self":
        gauges = {p: GAUGE_REASONS[(kind, p)] for p in ("spin_zero_deg", "step_scale") if p in params}
    else:  # a reference object centred on the spin axis looks alike at every spin
        on_axis = float(np.hypot(*known.centroid[:2])) < 1e-6 and np.allclose(known.covariance[0, 0],
                                                                             known.covariance[1, 1])
        gauges = {"spin_zero_deg": GAUGE_REASONS[(kind, "spin_zero_deg")]} if on_axis and "spin_zero_deg" in params \
            else {}
    free = tuple(p for p in params if p in GEOMETRY_MOMENTS and p not in gauges)
    spare = spare_conditions(len(moments.k), free, known)
    if free and spare < MIN_SPARE_CONDITIONS:  # fitted exactly: any estimate, every interval collapsed
        unknowns = 2 * len(moments.k) - spare
        needed = math.ceil((unknowns + MIN_SPARE_CONDITIONS) / 2)
        among = " (the object's centroid and spread among them)" if known is None else ""
        why = (f"{len(moments.k)} complete dips give {2 * len(moments.k)} moment conditions for {unknowns} unknowns"
               f"{among}, fewer than {MIN_SPARE_CONDITIONS} to spare to tell the rig from the noise: dip at least "
               f"{needed} orientations")
        gauges.update({p: why for p in free})
        free = ()
    fixed = {f: float(getattr(initial, f)) for f in GEOMETRY_MOMENTS}
    confounded = confounded_heights(moments, free, known=known, fixed=fixed, t0_sd_mm=t0_sd_mm,
                                    position_sd_mm=position_sd_mm) if free else {}
    gauges.update(confounded)  # kept at the configured values, as the parameters of too few dips
    free = tuple(p for p in free if p not in confounded)
    joint = fit_moments(moments, free, known=known, fixed=fixed, seed=seed, t0_sd_mm=t0_sd_mm,
                        position_sd_mm=position_sd_mm) if free else None
    fit, undetermined, caveats, held = _hold_undetermined(joint, moments, known, fixed, kind, seed, t0_sd_mm,
                                                          position_sd_mm)
    spread = _held_spread(fit, moments, known, {**fixed, **{p: v for p, (v, _, _) in held.items()}},
                          tuple(undetermined), t0_sd_mm, position_sd_mm) if fit is not None and fit is not joint else {}
    undetermined.update(gauges)
    if joint is not None:
        floors = _moment_floors(kind, joint, known, raw)
        geometry = geometry.with_values(**{p: v for p, (v, _, _) in held.items()})
        for p, (value, interval, sd) in held.items():
            _record(report, p, value, interval, sd, floors[p])
        report.caveats.update(caveats)
    if fit is not None:
        geometry = geometry.with_values(**{p: fit.values[p] for p in fit.free})
        report.moment_rms = fit.residual_rms
        for p in fit.free:
            interval, sd = fit.intervals[p], fit.bootstrap_sd[p]
            if fit is not joint:  # refitted with parameters held: their spread in the joint fit moves these too
                interval = (min(interval[0], joint.intervals[p][0]), max(interval[1], joint.intervals[p][1]))
                sd = max(sd, joint.bootstrap_sd[p])
                if spread.get(p, 0.0) > 0:  # and the held ones' configured values are known only to CONFIGURED_SD
                    interval = (interval[0] - 1.645 * spread[p], interval[1] + 1.645 * spread[p])
                    sd = math.hypot(sd, spread[p])
                if 0.5 * (interval[1] - interval[0]) > TOLERANCE[p] and p not in caveats:
                    caveats[p] = (f"its interval is wider than its tolerance {TOLERANCE[p]:g}: it covers what "
                                  f"{', '.join(sorted({*undetermined, *held}))} (held) may be")
            _record(report, p, fit.values[p], interval, sd, floors[p])
        report.correlations.update({p: {q: c for q, c in row.items() if q in fit.free}
                                    for p, row in fit.correlations.items() if p in fit.free})
        report.caveats.update(caveats)
    placed = fit if fit is not None else joint
    radius = _object_radius(placed, known)
    undetermined.update(report.undetermined)
    for p, why in undetermined.items():
        report.estimates[p] = float(getattr(initial, p))
        report.undetermined[p] = why
        report.shape_motion[p] = shape_motion(p, radius)
    if known is not None and known.radial() is not None and placed is not None:
        report.reference_centroid_mm = [float(v) for v in placed.centroid]
    height = float(placed.values["t0_mm"]) if placed is not None else 0.0  # a reference's fitted start height
    return State(geometry, t0_mm=height), report, moments


#: How far a configured value may be from the truth (standard deviation): that of a uniform draw over the
#: calibrated range (pivot +-60 mm, offset +-40 mm, tilt and spin zeros +-5 deg; the step scale's search
#: range +-5 %). An estimate the dips know less well is shrunk toward the configured value by this prior
#: (:func:`_hold_undetermined`).
CONFIGURED_SD = {"pivot_mm": 60 / math.sqrt(3), "tilt_axis_offset_mm": 40 / math.sqrt(3),
                 "tilt_zero_deg": 5 / math.sqrt(3), "spin_zero_deg": 5 / math.sqrt(3),
                 "step_scale": 0.05 / math.sqrt(3)}


def _hold_undetermined(joint, moments: DipMoments, known: KnownObject | None, fixed: dict[str, float], kind: str,
                       seed: int, t0_sd_mm: float,
                       position_sd_mm: float = 0.0) -> tuple[object, dict[str, str], dict[str, str], dict[str, tuple]]:
    """``(fit, undetermined, caveats, held)``: the joint fit with the parameters the dips do not pin to their
    tolerance settled one at a time, the widest against its tolerance first, then the rest refitted (the
    offset may be pinned once the tilt zero is).

    Each is held at the precision-weighted mean of its estimate and its configured value (prior sd
    :data:`CONFIGURED_SD`; the data's sd the largest of the bootstrap's, the joint fit's (a parameter held in a
    later round was refitted around the ones held before it, whose errors it absorbs: a 10 mm bunny's pivot came
    out 52.9 mm, interval [49.9, 55.7], after its offset was held, for a true 30; the joint fit's interval
    [28.0, 77.6]) and, for the nonlinear ones, ``tolerance / sqrt(profile rise)``). When the data carry less than half
    the weight, or the estimate reached the edge of its search range, it is held at the configured value and named
    ``undetermined``; else it is estimated: ``held[name] = (value, 90% interval, sd)``, named in ``caveats``.

    The refits fit the reference's start height and mounting with their priors as the joint fit does
    (``t0_sd_mm``, ``position_sd_mm``): a held tilt zero cannot absorb a height error, which would otherwise
    bias the step scale through the dips' first moments.
    """
    fit, undetermined, caveats, held = joint, {}, {}, {}
    values = dict(fixed)
    while fit is not None:
        why = {p: w for p, w in fit.undetermined(kind).items() if p not in caveats}
        if not why:
            break
        name = max(why, key=lambda p: (fit.at_search_edge(p), _half_width(fit, p) / TOLERANCE[p]))
        rise = fit.profile_rise.get(name, np.inf)
        data_sd = max(_half_width(fit, name) / 1.645, TOLERANCE[name] / math.sqrt(max(rise, 1e-12)),
                      _half_width(joint, name) / 1.645)  # refitted around a held one: the joint fit's spread too
        weight = CONFIGURED_SD[name]**2 / (CONFIGURED_SD[name]**2 + data_sd**2)
        if fit.at_search_edge(name) or weight < 0.5:
            undetermined[name] = why[name]
        else:
            values[name] = fixed[name] + weight * (fit.values[name] - fixed[name])
            half = 1.645 * math.sqrt(weight) * data_sd  # the posterior's
            held[name] = (values[name], (values[name] - half, values[name] + half), half / 1.645)
            caveats[name] = (f"is not pinned to its tolerance {TOLERANCE[name]:g} ({why[name]}): its estimate "
                             f"{fit.values[name]:.4g} is shrunk toward the configured {fixed[name]:g} by the "
                             f"configuration's own uncertainty (sd {CONFIGURED_SD[name]:g}) to {values[name]:.4g}")
        kept = tuple(p for p in fit.free if p != name)
        fit = fit_moments(moments, kept, known=known, fixed=values, seed=seed, t0_sd_mm=t0_sd_mm,
                          position_sd_mm=position_sd_mm) if kept else None
    return fit, undetermined, caveats, held


def _held_spread(fit, moments: DipMoments, known: KnownObject | None, values: dict[str, float],
                 held: tuple[str, ...], t0_sd_mm: float, position_sd_mm: float) -> dict[str, float]:
    """Free parameter of ``fit`` -> how far (standard deviation, its own units) it moves when each parameter
    ``held`` at its configured value in ``values`` (named undetermined by :func:`_hold_undetermined`) is moved by
    that value's own uncertainty (:data:`CONFIGURED_SD`) and the rest refitted (no bootstrap), in quadrature over
    the held ones. The refit around a held value cannot see its error, and the joint fit's bootstrap over a flat
    valley may not either: a centred 19 mm ball (24 dips, pivot 105 mm, tilt zero 3.1 deg held at 0) put the
    offset at -0.07 mm with the interval [-1.27, 1.33] for a true 6.14 (each degree of tilt zero moves the offset
    by the pivot's 1.8 mm)."""
    out = {p: 0.0 for p in fit.free}
    for name in held:
        if name not in CONFIGURED_SD:
            continue
        moved = [fit_moments(moments, fit.free, known=known, fixed={**values, name: values[name] + sign *
                             CONFIGURED_SD[name]}, bootstrap=0, t0_sd_mm=t0_sd_mm, position_sd_mm=position_sd_mm)
                 for sign in (-1.0, 1.0)]
        for p in fit.free:
            out[p] = math.hypot(out[p], 0.5 * (moved[1].values[p] - moved[0].values[p]))
    return out


def _half_width(fit, name: str) -> float:
    low, high = fit.intervals.get(name, (fit.values[name], fit.values[name]))
    return 0.5 * (high - low)


def _moment_floors(kind: str, fit, known: KnownObject | None, raw: RawScan) -> dict[str, float]:
    """The model-error half-widths (:data:`MODEL_FLOOR`) of the moment stage's parameters at ``fit``.

    Lengths scale with the step scale, so the pivot's floor grows with ``|pivot|`` times the step
    scale's; a tilt-zero error turns the pivot's arm into an offset error, so the offset's grows with
    ``|pivot|`` times the tilt zero's (in radians).
    """
    floors = dict(MODEL_FLOOR[kind])
    if known is not None:  # the stage's steps leave up to h^2 / 12 of every dip's variance (h: the step) uncertain
        step = float(np.median(np.concatenate([np.diff(o.stage_mm) for o in raw.orientations])))
        floors["step_scale"] = math.hypot(floors["step_scale"], step**2 / 12.0 / np.trace(known.covariance) * 3.0)
    pivot = abs(fit.values.get("pivot_mm", 0.0))
    if "step_scale" in fit.free:
        floors["pivot_mm"] = math.hypot(floors["pivot_mm"], pivot * floors["step_scale"])
    if "tilt_zero_deg" in fit.free and "tilt_zero_deg" in floors:
        floors["tilt_axis_offset_mm"] = math.hypot(floors["tilt_axis_offset_mm"],
                                                   pivot * math.radians(floors["tilt_zero_deg"]))
    return floors


def _record(report: CalibrationReport, name: str, value: float, interval: tuple[float, float], sd: float,
            floor: float) -> None:
    """An estimate with its 90% interval widened by the model-error half-width ``floor`` (in quadrature)."""
    low, high = interval
    centre, half = 0.5 * (low + high), 0.5 * (high - low)
    widened = math.hypot(half, floor)
    shift = value - centre  # keep the estimate inside, the percentile interval may be skewed
    report.estimates[name] = float(value)
    report.intervals[name] = (float(min(value, centre - widened + min(shift, 0.0))),
                              float(max(value, centre + widened + max(shift, 0.0))))
    report.standard_errors[name] = float(math.hypot(sd, floor / 1.645))


def _object_radius(fit, known: KnownObject | None) -> float:
    """The radius (mm) of a ball with the object's largest moment of volume: ``sqrt(5 lambda_max)``."""
    cov = known.covariance if known is not None else (None if fit is None else fit.covariance)
    if cov is None:
        return float("nan")
    return float(np.sqrt(5.0 * max(np.linalg.eigvalsh(cov).max(), 0.0)))


def _placed_occupancy(shape, known: KnownObject, centroid_mm: list[float] | None, grid: Grid,
                      supersample: int) -> torch.Tensor:
    """The reference's occupancy on ``grid`` moved from its assumed centroid to ``centroid_mm`` (the moment
    stage's, which fits its distance from the spin axis), by a linear interpolation of the voxels."""
    occupancy = shape.occupancy(grid, supersample=supersample).to(torch.float64)
    if centroid_mm is None:
        return occupancy
    shift = (np.asarray(centroid_mm) - known.centroid)[::-1] / grid.voxel_size  # array axes: z, y, x
    return torch.from_numpy(scipy.ndimage.shift(occupancy.numpy(), shift, order=1, mode="constant"))


def known_object(shape, supersample: int = 2) -> KnownObject:
    """The centroid, covariance and volume of a reference :class:`~dipnet.shapes.Shape` (a
    ball's in closed form, any other's from its occupancy on a 64^3 grid around it)."""
    from dipnet.shapes import Ball

    if isinstance(shape, Ball):
        return KnownObject.ball(shape.r, shape.center)
    grid = Grid(64, 3, extent=2.05 * float(shape.radius()))
    occ = shape.occupancy(grid, supersample=supersample).numpy().astype(np.float64)
    z, y, x = np.meshgrid(*(grid.centers().numpy(),) * 3, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    weights = occ.ravel() / occ.sum()
    centroid = weights @ points
    centred = points - centroid
    return KnownObject(centroid, (centred * weights[:, None]).T @ centred, float(shape.volume))


def _name_the_size_trade(report: CalibrationReport, configured: float, known: KnownObject, section: bool) -> None:
    """A caveat on a step scale whose interval excludes the configured one (and on the section, if ``section``
    is estimated): a reference's dips measure its size in stage steps, so a reference of another size than
    given reads as a step scale (the audit's ball given as 31 mm for 30 mm: step scale 1.017, section 10 %
    high, each with a tight interval)."""
    if "step_scale" not in report.intervals or "step_scale" in report.undetermined:
        return
    low, high = report.intervals["step_scale"]
    if low <= configured <= high:
        return
    scale = report.estimates["step_scale"]
    size = math.sqrt(np.trace(known.covariance) * 5.0 / 3.0)  # a ball's radius from its covariance (mm)
    ratio = configured / scale
    trade = (f"its interval excludes the configured {configured:g}: the stage's steps are "
             f"{100 * (scale / configured - 1):+.2g} % off what was commanded, or the reference is "
             f"{100 * (ratio - 1):+.2g} % off the size given (its dips measure it in stage steps; for a ball, a radius "
             f"of {size * ratio:.4g} mm instead of {size:.4g} mm gives the same dips, and the section follows about 3 "
             "times as much): the interval does not cover an error in the reference's size; check its diameter")
    report.caveats["step_scale"] = "; ".join(filter(None, (report.caveats.get("step_scale"), trade)))
    if section:
        report.caveats["cross_section_mm2"] = ("its interval does not cover an error in the reference's size (see "
                                               "the step scale): a reference 1 % larger than given reads a section "
                                               "about 3 % larger")


# ---------------------------------------------------------------------------- reference object
#: How a balance's tank section is known when no tolerance is given: the calibrated range.
BALANCE_SECTION_RANGE = "the calibrated range +-20 %"


def balance_section_note(section_tolerance: float | None, reference: bool = True) -> str:
    """Why a balance's section is not estimated, and how well the intervals take it as known: the given
    ``section_tolerance`` (a relative 90 % half-width) or, for ``None``, :data:`BALANCE_SECTION_RANGE` (for a
    ``reference`` calibration, with the option that narrows it)."""
    if section_tolerance is None:
        better = "; a section known better narrows the step scale's interval (calibrate.py --section-tolerance)"
        known = f"sd {100 * BALANCE_SECTION_SD:.1f} %: {BALANCE_SECTION_RANGE}{better if reference else ''}"
    else:
        known = f"sd {100 * section_tolerance / 1.645:.2g} %: the given tolerance +-{100 * section_tolerance:.3g} %"
    return ("not estimated: a balance reads the displaced volume, which needs no section; the water line's rise "
            f"(volume over section) uses the configured one, and the other parameters' intervals carry its error "
            f"({known})")


#: A tolerance of the section at or above this is taken for a percentage (20 meant as 20 %).
_SECTION_TOLERANCE_LIMIT = 1.0


def _warn_misplaced(given: np.ndarray, fitted: list[float] | None, tolerance_mm: float) -> None:
    """Warn when a reference's fitted centre ``(3,)`` (mm, ``None``: on the spin axis, not fitted) is farther than
    ``tolerance_mm`` from the ``given`` one ``(3,)``: it is not mounted where stated."""
    if fitted is None:
        return
    distance = float(np.linalg.norm(np.asarray(fitted) - given))
    if distance <= tolerance_mm:
        return
    at = ", ".join(f"{v:.2f}" for v in fitted)
    message = (f"reference calibration: the reference's centre was fitted at [{at}] mm, {distance:.1f} mm from the "
               f"given centre {[float(v) for v in given]} mm (more than the position tolerance {tolerance_mm:g} mm): "
               f"it is not mounted where stated. The geometry is still estimated, because the dips fit its distance "
               f"from the spin axis with it (a tilt-zero error moves their heights as cos r, a distance error as "
               f"sin r); its height and its direction from the axis are not fitted that way (an error in them moves "
               f"the pivot and the spin zero), so check the mounting and the given centre (calibrate.py --centre)")
    log_and_warn(log, message, stacklevel=3)


def check_reference_options(max_relative_residual: float, start_height_tolerance_mm: float,
                            position_tolerance_mm: float, section_tolerance: float | None = None) -> None:
    """Raise :class:`CalibrationError` (a ``ValueError``) for options of :func:`calibrate_reference` no fit can
    honour, before any work: ``max_relative_residual`` (a fraction) not above 0 or NaN (every fit refused, after
    the fit), a tolerance (mm) negative or NaN, a ``section_tolerance`` (a fraction) outside ``[0, 1)`` (2 meant as
    2 %). Each message names the option and ``calibrate.py``'s flag."""
    if not max_relative_residual > 0:  # NaN fails too; inf accepts any fit
        raise CalibrationError(f"max_relative_residual must be a positive fraction (the default 0.05: a 5 % relative "
                               f"profile residual), got {max_relative_residual!r} (calibrate.py --max-residual)")
    for name, flag, tolerance in (("start_height_tolerance_mm", "--height-tolerance", start_height_tolerance_mm),
                                  ("position_tolerance_mm", "--position-tolerance", position_tolerance_mm)):
        if not tolerance >= 0:
            raise CalibrationError(f"{name} must be >= 0 (mm), got {tolerance!r} (calibrate.py {flag})")
    if section_tolerance is not None and not 0 <= section_tolerance < _SECTION_TOLERANCE_LIMIT:  # NaN fails too
        hint = (f" ({section_tolerance:g} would be {100 * section_tolerance:g} %; for {section_tolerance:g} % give "
                f"{section_tolerance / 100:g})" if section_tolerance >= _SECTION_TOLERANCE_LIMIT else "")
        raise CalibrationError(f"section_tolerance must be a fraction in [0, 1) (the 90 % half-width of the tank "
                               f"section's relative error: 0.02 for +-2 %), got {section_tolerance!r}{hint} "
                               "(calibrate.py --section-tolerance)")


def _lag_note(raw: RawScan, lag_s: float) -> str:
    """Why the sensor lag is not estimated, and what an unknown one does to a reference's intervals, for a level
    scan whose readings are ``dt`` s apart (the median over its dips) and a configured lag ``lag_s`` (s)."""
    if lag_s > 0:
        return f"not estimated: the configured {lag_s:g} s is undone in every dip (calibrate.py --sensor-lag)"
    gaps = np.concatenate([np.diff(o.time_s) for o in raw.orientations])
    dt = float(np.median(gaps)) if gaps.size else float("nan")
    return ("not estimated, taken as 0: a lag delays every dip's rise alike, which the start height's tolerance "
            f"carries, and spreads it, which no interval carries: above about half of this scan's {dt:.3g} s per "
            "reading it puts the step scale low (a 1.5 s lag at 2 s per reading: 0.16 %, 4 standard errors). Give a "
            "known lag (calibrate.py --sensor-lag), or let every reading settle longer")


#: A reference's profile residual above ``max_relative_residual`` is still accepted within this factor of what the
#: readings' own noise gives (:func:`noise_residual`): at 10 dB a 30 mm ball's profiles miss their true geometry by
#: 0.06-0.10 (24 dips, 32^3-48^3), and the noise copy's residual was 0.83-1.12 times the true geometry's from
#: 10 to 40 dB (16-60 dips, 48^3; the profiles' own estimate under-read it up to 4 times).
NOISE_FACTOR = 1.5


def _without_truncated(raw: RawScan) -> RawScan:
    """``raw`` without the dips that end before the reference is under water
    (:func:`~dipnet.preprocessing.recorded.truncated_orientations`), warned about by name; refused when more than
    :data:`~dipnet.preprocessing.recorded.MAX_DROPPED_SHARE` of them do. Their rise is short of the object's
    volume, which the fit took for a smaller or misplaced ball: with 2 of 16 dips short the fit was refused as
    "does not fit the dips", blaming the ball's size, its mounting or the stage."""
    cut = truncated_orientations(raw)
    if not cut:
        return raw
    listed = ", ".join(str(k) for k in cut[:8]) + (", ..." if len(cut) > 8 else "")
    found = (f"{len(cut)} of {len(raw.orientations)} reference dips end before the object is under water "
             f"(dips {listed}): a deeper protocol.stop_mm records them whole")
    if len(cut) > MAX_DROPPED_SHARE * len(raw.orientations):
        raise CalibrationError(f"{found}; too few are left to calibrate from")
    message = f"{found}; they are left out"
    log_and_warn(log, message, stacklevel=3)
    return replace(raw, orientations=[o for o in raw.orientations if o.k not in cut])


def _rounding_share(raw: RawScan, rises: np.ndarray) -> float:
    """The 90 % half-width (relative) of the section that the reading quantum ``q`` leaves when the readings are
    quieter than it: every dip's rise is then a difference of two levels each rounded alike in every dip, an error
    of up to ``q`` that no average over readings or dips removes (its sd ``q / sqrt(6)``, over the mean rise).
    Noise of ``q / 2`` or more dithers the rounding, which then averages out: 0. A 16 mm ball rising 0.13 mm, read
    to 0.001 mm without noise, came out 0.1 % small with an interval of +-0.02 %."""
    quantum = raw.header.resolution or 0.0
    if not quantum > 0 or not len(rises) or not float(np.mean(rises)) > 0:
        return 0.0
    quiet = float(np.median([reading_sigma(o.values) for o in raw.orientations])) < 0.5 * quantum
    return 1.645 * quantum / math.sqrt(6.0) / float(np.mean(rises)) if quiet else 0.0


def noise_residual(model: ProfileModel, state: State, seed: int = 0) -> float:
    """The relative profile residual the readings' own noise gives at ``state``: ``|m' - m| / |m|`` for the
    profiles ``m`` of ``model``'s readings and ``m'`` of the same readings with as much white noise again (each dip's
    :func:`~dipnet.calibration.moments.reading_sigma`, and the reading quantum's ``q / sqrt(12)`` at least: a quiet
    quantised sensor's rounding, which a 16 mm ball's 0.13 mm rise read to 0.001 mm missed its fit by, was
    refused as a misfit against a noise of 0), through the same preprocessing (its monotone fit included,
    which removes part of the noise: the slabs' own estimate, :func:`~dipnet.core.measurement.estimate_slab_sigma`,
    under-reads it 2-4 times at 10-30 dB)."""
    rng = np.random.default_rng(seed)
    rounding = (model.raw.header.resolution or 0.0) / math.sqrt(12.0)  # a quantised sensor's noise at least
    noisy = replace(model.raw, orientations=[
        replace(o, values=o.values + rng.normal(0.0, math.hypot(reading_sigma(o.values), rounding), o.values.shape))
        for o in model.raw.orientations])
    measured = model.measurement(state).profiles.numpy().reshape(-1)
    again = ProfileModel(noisy, model.grid, model.n_slabs, model.operator_factory, model.smooth,
                         drift_mm_per_s=model.drift_mm_per_s, check_step=False).measurement(state)
    return float(np.linalg.norm(again.profiles.numpy().reshape(-1) - measured) / max(np.linalg.norm(measured), 1e-300))


def calibrate_reference(raw: RawScan, shape, grid: Grid, params=DEFAULT_REFERENCE, *,
                        initial: RigGeometry | None = None, n_slabs: int | None = None,
                        operator_factory: Callable | None = None, supersample: int = 3,
                        max_relative_residual: float = 0.05, start_height_tolerance_mm: float = 0.5,
                        position_tolerance_mm: float = 0.5, section_tolerance: float | None = None,
                        seed: int = 0) -> tuple[RigGeometry, CalibrationReport]:
    """The rig geometry from dips of a reference object of known geometry and pose.

    The moment stage (module docstring) estimates the drift, pivot, offset, tilt zero, spin zero
    and step scale; the object's known volume gives the cross-section. What the dips cannot
    determine (a centred ball's spin zero, its tilt zero on a rig with pivot and offset near 0)
    is named, warned about and kept at ``initial``. Finally the object's profiles on ``grid``
    must match the calibrated dips.

    Args:
        raw: the reference object's raw scan (tilted dips for the pivot, offset and tilt zero).
        shape: the reference object (:class:`~dipnet.shapes.Shape`: e.g. ``Ball(30)``) in the
            object frame the rig holds it in.
        grid: the grid of the final check (a voxel << the object's size).
        params: parameters to estimate (:data:`PARAMETERS`).
        initial: the configured geometry (default the ideal rig).
        max_relative_residual: refuse when ``|A f - m| / |m|`` stays above this at the estimate (the
            object does not fit: wrong size, wrong pose, or the data are not of this object) and above
            :data:`NOISE_FACTOR` times what the readings' own noise gives (:func:`noise_residual`).
        start_height_tolerance_mm: how well the water line's height at the stage's zero is known (90%
            half-width, mm: the stage's zero against the water, and the shift a sensor lag gives every dip). A
            centred ball shows the tilt zero only through the start heights, so a height error of ``c`` mm
            moves it by about ``c / offset`` radians; a ball off the spin axis shows its start height itself.
        position_tolerance_mm: how well the object's centre is known in the object frame, along each axis
            (90% half-width, mm: its mounting). Mounted higher, it moves every dip's height as ``cos r``: the
            pivot is known only to this. An object off the spin axis, at a distance ``d`` mm, shows the spin
            zero to about ``tolerance / d`` radians (its distance from the axis is fitted, so its tilt zero
            does not depend on it); a centred object's tilt zero trades against its position. Both
            tolerances enter the moment fit as Gaussian priors on the start height and the object's position
            (:func:`~dipnet.calibration.moments.fit_moments`), so the intervals carry them and the dips
            decide what they determine.
        section_tolerance: for a balance's scan, how well the tank's free section is known (the 90% half-width
            of its relative error, e.g. 0.02 for +-2 %; the section is ``initial``'s ``cross_section_mm2``, else
            the scan's nominal one). A balance reads the displaced volume, and the water line's rise is that
            volume over the section, which the dips cannot tell from the step scale: the moment bootstrap draws
            it (a normal error of sd ``section_tolerance / 1.645``; ``None``: the calibrated range +-20 %, sd
            11.5 %, which leaves the step scale known to about +-0.8 %). A level sensor reads the rise itself
            and its section is estimated from the object's volume: a tolerance is refused for it.

    Returns ``(geometry, report)``. Raises :class:`CalibrationError` when the object does not fit.
    """
    params = _check_params(params)
    initial = initial or RigGeometry()
    if any(o.meta.get("t_start_mm", raw.header.t_start_mm) is None for o in raw.orientations):
        raise CalibrationError("the scan does not record its dips' start heights (the authors' CSV does not), which "
                               "a reference calibration measures the rig by: record the ball with scripts/scan.py")
    known = known_object(shape)
    check_reference_options(max_relative_residual, start_height_tolerance_mm, position_tolerance_mm,
                            section_tolerance)
    raw = _without_truncated(raw)
    levels = raw.header.quantity == "level_mm"  # a balance reads volumes: the section is neither needed nor shown
    if levels and section_tolerance is not None:
        raise CalibrationError(f"section_tolerance={section_tolerance:g} is for a balance's scan: this scan reads the "
                               "water level, whose rise needs no section, and the section is estimated from the "
                               "reference's volume; leave it out (calibrate.py --section-tolerance)")
    state, report, moments = _moment_stage(raw, params, initial, "reference", known, seed,
                                           t0_sd_mm=start_height_tolerance_mm / 1.645,
                                           position_sd_mm=position_tolerance_mm / 1.645,
                                           section_sd=None if section_tolerance is None else section_tolerance / 1.645)
    _warn_misplaced(known.centroid, report.reference_centroid_mm, position_tolerance_mm)
    _name_the_size_trade(report, initial.step_scale, known, "cross_section_mm2" in params and levels)
    if "cross_section_mm2" in params and not levels:
        report.not_estimated["cross_section_mm2"] = balance_section_note(section_tolerance)
    if levels:
        report.not_estimated["sensor_lag_s"] = _lag_note(raw, initial.sensor_lag_s)
    if "cross_section_mm2" in params:
        rng = np.random.default_rng(seed)
        rises = np.asarray(moments.rise)  # mm of level per dip, drift removed
        section = known.volume / rises.mean() if levels else None
        if section is not None:
            draws = [known.volume / rises[rng.integers(0, len(rises), len(rises))].mean() for _ in range(200)]
            state = replace(state, geometry=state.geometry.with_values(cross_section_mm2=float(section)))
            floor = math.hypot(MODEL_FLOOR["reference"]["cross_section_mm2"], _rounding_share(raw, rises))
            _record(report, "cross_section_mm2", float(section), tuple(np.percentile(draws, [5, 95])),
                    float(np.std(draws)), floor * section)
    model = ProfileModel(raw, grid, n_slabs, operator_factory, drift_mm_per_s=state.geometry.level_drift_mm_per_s)
    occupancy = _placed_occupancy(shape, known, report.reference_centroid_mm, grid, supersample)
    measured = model.measurement(state).profiles.numpy().reshape(-1)
    fit = float(np.linalg.norm(model.residual(state, occupancy, 1.0)) / max(np.linalg.norm(measured), 1e-300))
    if fit > max_relative_residual:
        noise = noise_residual(model, state, seed)
        if fit > NOISE_FACTOR * noise:
            found = [f"{p} {why}" for p, why in {**report.undetermined, **report.caveats}.items()]
            raise CalibrationError(
                f"the reference object does not fit the dips: relative profile residual {fit:.3f} > "
                f"{max_relative_residual} at the calibrated geometry, where the readings' own noise gives about "
                f"{noise:.3f}" + (f"; the moment stage found: {'; '.join(found)}" if found else "") +
                ". Check the object's size and pose, the recording, and that the rig is inside the calibrated range; "
                "a larger max_relative_residual (calibrate.py --max-residual) accepts it")
        log.info("reference calibration: relative profile residual %.3f above %g, within %g x the %.3f the readings' "
                 "own noise gives: accepted", fit, max_relative_residual, NOISE_FACTOR, noise)
    report.residual_rms = fit
    _warn_undetermined(report, "reference calibration")
    return state.geometry, report
