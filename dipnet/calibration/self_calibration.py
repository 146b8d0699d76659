"""Self-calibration: the moment stage, then the geometry and the volume gain fitted jointly with an
unknown shape."""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import scipy.ndimage
import torch

from dipnet.calibration.model import (DEFAULT_SELF, PARTIAL_VOLUME_GAIN, SELF_SECTION_FLOOR, CalibrationError,
                                      CalibrationReport, ProfileModel, State, _check_params, _get, _warn_undetermined,
                                      _with, fit_geometry, identifiability, self_section_bias)
from dipnet.calibration.moments import TOLERANCE
from dipnet.calibration.reference import SHAPE_MOTION, _moment_stage, _record, balance_section_note
from dipnet.core.geometry import RigGeometry
from dipnet.core.orientations import unmeasured_band_deg
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.rawscan import RawScan
from dipnet.core.reconstruction import Reconstruction
from dipnet.solvers.weights import with_weight
from dipnet.solvers.surface_refit import without_surface_refit

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- self-calibration
@dataclass
class SelfCalibration:
    """The result of :func:`self_calibrate`."""

    geometry: RigGeometry
    t0_mm: float
    measurement: DipMeasurement
    reconstruction: Reconstruction
    report: CalibrationReport
    history: list[dict] = field(default_factory=list)


#: The coarsest grid (voxels per axis) and the fewest dips at which the self-calibrated cross-section's interval was
#: validated: the calibration benchmark (random rigs, 123 dips, 48^3; its ``--quick`` at 32^3). An audit at
#: 20^3 with 40 dips, 24^3 with 60 and 32^3 with 80 found the interval missing the truth in 13 of 17 rigs (errors
#: up to 16 %): there the shape absorbs about half a wrong section, which one joint step then recovers only in
#: part. Below either, the section is named undetermined and kept (:func:`self_calibrate`).
SECTION_MIN_RESOLUTION = 32
SECTION_MIN_DIPS = 100


def check_section_change(max_section_change: float | None) -> None:
    """Raise :class:`CalibrationError` unless ``max_section_change`` is ``None`` or a fraction in (0, 1): a relative
    change of 1 or more lets the section fall to nothing, so the guard is gone (``20`` meant as 20 % accepted any
    section without a word)."""
    if max_section_change is None:
        return
    value = max_section_change
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:  # NaN fails too
        hint = (f" ({value:g} would accept any section; for {value:g} % give {value / 100:g})"
                if isinstance(value, (int, float)) and not isinstance(value, bool) and 1 <= value < math.inf else "")
        raise CalibrationError(f"max_section_change must be a fraction in (0, 1) or null (the relative change of the "
                               f"cross-section beyond which it is kept, e.g. 0.2), got {value!r}{hint}")


def self_calibrate(raw: RawScan, grid: Grid, solver, params=DEFAULT_SELF, *, n_slabs: int | None = None,
                   operator_factory: Callable | None = None, smooth: bool = False, finish=None,
                   initial: RigGeometry | None = None, iterations: int = 1, dip_offset_sigma_mm: float | None = None,
                   shape: str = "binary", max_nfev: int = 20, gain_solver=None,
                   max_section_change: float | None = None, section_min_resolution: int = SECTION_MIN_RESOLUTION,
                   section_min_dips: int = SECTION_MIN_DIPS, seed: int = 0) -> SelfCalibration:
    """Estimate the rig geometry jointly with the shape.

    1. The moment stage (module docstring): drift, pivot, offset and tilt zero from the dips'
       first two moments, with no grid and no shape. The spin zero and the step scale are
       gauges of an unknown object: named, with how far the shape could move, and kept.
    2. The cross-section jointly with the shape (a level sensor's scan: a balance reads the displaced volume,
       which does not depend on the section, so its section is named not estimated and kept; the joint step
       fitted a gain to the shape's partly filled voxels and claimed a section near the configured one, 20 %
       off the tank's with an interval that missed it): the shape step (``gain_solver`` or ``solver``
       with ``fit_gain``) fits one gain ``a`` on every predicted volume together with the shape;
       the calibrated cross-section is ``assumed / a``, corrected for the field's volume deficit in
       partly filled voxels (:func:`~dipnet.calibration.model.self_section_bias`). Fitted jointly, the gain and the
       shape's size compete through the profiles' *shapes* (a dilated object widens every profile, a gain
       only scales it; a nearly binary interior cannot exceed 1). Its interval is widened by the
       shape prior's bias (:data:`SELF_SECTION_FLOOR`). With ``dip_offset_sigma_mm`` a geometry
       step then fits per-dip height offsets to that shape. ``iterations`` such rounds.
       A section configured too small has a second explanation that the first does not: volumes too
       small for the shape, which the field can fit by thinning its whole interior below 1 instead of
       fitting a gain below 1. A round whose shape is so diluted (:func:`interior_density` below
       :data:`DILUTION_LIMIT`, with an interior the grid resolves: :func:`interior_share` at least
       :data:`MIN_INTERIOR_SHARE`) rescales the section past the dilution and is followed by one more
       round, which then sees volumes too large for a solid shape (identifiable: no density exceeds 1).
    3. A final shape step (no gain) with the calibrated geometry.

    Args:
        raw: the object's raw scan (complete dips that start before contact and end under water).
        grid, n_slabs, operator_factory, smooth: reconstruction grid, slabs, operators, smoothing.
        solver: any :class:`~dipnet.solvers.Solver` (the shape step); the cross-section needs
            an optimisation solver (``fit_gain``: voxel, implicit).
        params: parameters to estimate (:data:`PARAMETERS`; default all but the lag).
        finish: applied to every preprocessed measurement (:class:`ProfileModel`).
        initial: the configured geometry (default: the ideal rig); undetermined parameters keep it.
        shape: what the report's profile stage fits: ``"binary"`` or ``"occupancy"``.
        max_section_change: a cross-section further than this (relative) from the assumed one is
            not trusted: named undetermined and kept. Default (``None``): :data:`MAX_SECTION_CHANGE`,
            20 % for a scan with a missing cone wider than :data:`MISSING_CONE_DEG` (the three cats, with
            a 56 deg missing cone: the gain came out 1.46, a section 31 % below the tank's), else 50 %
            (a full hemisphere of dips determines the section; the calibration benchmark's rigs reach
            +-31 % of the configured section at the configured step scale).
        gain_solver: the solver of step 2 (default ``solver``); the final shape is ``solver``'s.
        section_min_resolution, section_min_dips: the coarsest grid and fewest dips at which the
            cross-section's interval was validated (:data:`SECTION_MIN_RESOLUTION`, :data:`SECTION_MIN_DIPS`);
            on a coarser grid or with fewer dips it is named undetermined and kept. Lower them only with a
            check of your own (a reference ball).
        seed: the bootstrap's.

    Returns:
        :class:`SelfCalibration` with the report of both stages.
    """
    if shape not in ("occupancy", "binary"):
        raise CalibrationError(f"shape must be 'occupancy' or 'binary', got {shape!r}")
    check_section_change(max_section_change)
    params = _check_params(params)
    initial = initial or RigGeometry()
    levels = raw.header.quantity == "level_mm"  # a balance's volumes do not depend on the section
    volume_params = ("cross_section_mm2",) if "cross_section_mm2" in params and levels else ()
    shape_solver = _with_gain(gain_solver or solver) if volume_params else (gain_solver or solver)
    shape_solver = without_surface_refit(shape_solver)  # the rounds read occupancies; the final solve refits
    state, report, _ = _moment_stage(raw, params, initial, "self", None, seed)
    if "cross_section_mm2" in params and not levels:
        report.not_estimated["cross_section_mm2"] = balance_section_note(None, reference=False)
    model = ProfileModel(raw, grid, n_slabs, operator_factory, smooth, finish, state.geometry.level_drift_mm_per_s)
    history: list[dict] = [{"stage": "moments", **{p: _get(state, p, model.nominal_area) for p in params}}]
    sigma, implausible, occupancy, partial = None, None, None, 0.0
    limit = section_change_limit(model.measurement(state).directions, max_section_change)
    configured = _get(state, "cross_section_mm2", model.nominal_area)
    rounds = iterations if volume_params or dip_offset_sigma_mm is not None else 0
    it, diluted = 0, False
    while it < rounds:
        measurement = model.measurement(state)
        recon = shape_solver.solve(measurement, model.operator(measurement.directions))
        occupancy = _shape_volume(recon, shape)
        partial, density, interior = partial_volume(recon), interior_density(recon), interior_share(recon)
        gain = float(recon.info.get("gain", 1.0))
        diluted = volume_params and density < DILUTION_LIMIT and interior >= MIN_INTERIOR_SHARE
        if diluted:  # rescaled past the dilution; the next round fits the gain from above
            factor = 1.0 / (gain * density * (1.0 - DILUTION_MARGIN))
            if it + 1 == rounds == iterations:  # one round more, once
                rounds += 1
        else:  # less the field's known volume deficit
            factor = 1.0 / gain / (1.0 - self_section_bias(partial))
        if volume_params:
            section = _get(state, "cross_section_mm2", model.nominal_area) * factor
            change = section / configured - 1.0
            if abs(change) > limit:
                implausible = (f"the joint shape step moved it by {change:+.1%} (more than max_section_change "
                               f"{limit:.0%}): the shape prior, not the data, decided the volume (e.g. a "
                               "missing cone leaves the object's density free)")
                section = configured
            else:
                implausible = None
            state = _with(state, {"cross_section_mm2": section})
        if dip_offset_sigma_mm is not None:
            state, sigma = fit_geometry(model, occupancy, state, ("t0_mm",), dip_offset_sigma_mm=dip_offset_sigma_mm,
                                        sigma=sigma, max_nfev=max_nfev)
        history.append({"stage": f"shape {it}", "gain": gain, "partial_volume": partial,
                        "interior_density": density, "interior_share": interior,
                        "section_bias": 0.0 if diluted else self_section_bias(partial),
                        **{p: _get(state, p, model.nominal_area) for p in params}})
        it += 1
    if volume_params and diluted and implausible is None:
        implausible = (f"the last joint shape step still thinned the shape's interior to {density:.2f} (below "
                       f"{DILUTION_LIMIT:g}): the volumes are too small for any solid shape at this section")
    for row in history:
        log.info("self-calibration %s", ", ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}"
                                                  for k, v in row.items()))
    if volume_params:
        coarse = _coarse_setting(grid, model.measurement(state).directions.shape[0], section_min_resolution,
                                 section_min_dips)
        state = _section_report(report, model, state, occupancy, sigma, initial, implausible or coarse, partial)
    measurement = model.measurement(state)
    recon = solver.solve(measurement, model.operator(measurement.directions))
    _warn_undetermined(report, "self-calibration")
    measurement.metadata = {**measurement.metadata, "self_calibration": report.to_dict(),
                            "geometry": state.geometry.to_dict(), "t0_mm": state.t0_mm}
    recon.info = {**recon.info, "self_calibration": report.to_dict()}
    return SelfCalibration(state.geometry, state.t0_mm, measurement, recon, report, history)


class SelfCalibrator:
    """Self-calibration as a step of a reconstruction job (``calibration=self``): the options of
    :func:`self_calibrate`, applied by :meth:`run` to a source's recording.

    Args:
        params, iterations, dip_offset_sigma_mm, shape, gain_solver: as for :func:`self_calibrate`.
        max_section_change, section_min_resolution, section_min_dips: as for :func:`self_calibrate`.
        tank: the tank's identity for the written calibration file (``None``: the scan's).
    """

    def __init__(self, params=DEFAULT_SELF, iterations: int = 1, gain_solver=None,
                 max_section_change: float | None = None, section_min_resolution: int = SECTION_MIN_RESOLUTION,
                 section_min_dips: int = SECTION_MIN_DIPS,
                 shape: str = "binary", dip_offset_sigma_mm: float | None = None, tank: str | None = None) -> None:
        self.params, self.iterations, self.gain_solver = _check_params(params), int(iterations), gain_solver
        check_section_change(max_section_change)
        self.max_section_change = None if max_section_change is None else float(max_section_change)
        self.section_min_resolution, self.section_min_dips = int(section_min_resolution), int(section_min_dips)
        self.shape = str(shape)
        self.dip_offset_sigma_mm = None if dip_offset_sigma_mm is None else float(dip_offset_sigma_mm)
        self.tank = tank

    def run(self, recording, grid: Grid, solver, n_slabs: int, operator_factory: Callable) -> SelfCalibration:
        """:func:`self_calibrate` on ``recording`` (a :class:`dipnet.preprocessing.sources.Recording`:
        raw scan, configured geometry, smoothing, finishing step)."""
        return self_calibrate(recording.raw, grid, solver, self.params, n_slabs=n_slabs,
                              operator_factory=operator_factory, smooth=recording.smooth, finish=recording.finish,
                              initial=recording.initial, iterations=self.iterations,
                              dip_offset_sigma_mm=self.dip_offset_sigma_mm, shape=self.shape,
                              gain_solver=self.gain_solver, max_section_change=self.max_section_change,
                              section_min_resolution=self.section_min_resolution,
                              section_min_dips=self.section_min_dips)


def partial_volume(recon: Reconstruction) -> float:
    """Share of a reconstruction's volume in partly filled voxels (occupancy between 0.1 and 0.9)."""
    occ = recon.occupancy.detach().to(torch.float64)
    total = float(occ.sum())
    return float(occ[(occ > 0.1) & (occ < 0.9)].sum()) / total if total > 0 else 1.0


def interior_density(recon: Reconstruction) -> float:
    """The occupancy a reconstruction's interior settles at: the 90th percentile over voxels above 0.5
    (1 for a solid shape; 1 if no voxel is above 0.5)."""
    occ = recon.occupancy.detach().to(torch.float64).flatten()
    inside = occ[occ > 0.5]
    return float(torch.quantile(inside, 0.9)) if inside.numel() else 1.0


def interior_share(recon: Reconstruction) -> float:
    """Share of a reconstruction's volume in its resolved interior: the voxels above 0.5 whose six face neighbours
    are above 0.5 too (0 for an empty one). A thin object has none (the hammer at 32^3 and 48^3: its densest voxels
    are its thin parts' partly filled ones), so its :func:`interior_density` says nothing of a dilution."""
    occ = recon.occupancy.detach().to(torch.float64)
    total = float(occ.sum())
    if not total > 0:
        return 0.0
    inside = scipy.ndimage.binary_erosion((occ > 0.5).numpy())
    return float(occ[torch.from_numpy(inside)].sum()) / total


def _coarse_setting(grid: Grid, n_dips: int, min_resolution: int, min_dips: int) -> str | None:
    """Why a self-calibrated cross-section on ``grid`` from ``n_dips`` dips cannot be trusted, or ``None``."""
    if grid.n >= min_resolution and n_dips >= min_dips:
        return None
    return (f"the joint shape step was validated at {min_resolution}^3 and {min_dips} dips and more; at {grid.n}^"
            f"{grid.ndim} with {n_dips} dips the shape absorbs part of a wrong section (an audit of 17 rigs at "
            "20^3-32^3 with 40-80 dips: errors up to 16 %, 13 outside their 90 % intervals, half the way back to the "
            "configured section): calibrate the section with a reference ball (scripts/calibrate.py), or dip more "
            "orientations on a finer grid")


def _section_report(report: CalibrationReport, model: ProfileModel, state: State, occupancy: torch.Tensor,
                    sigma: float | None, initial: RigGeometry, implausible: str | None, partial: float) -> State:
    """Enter the self-calibrated cross-section into ``report``: the Gauss-Newton standard error with
    the shape's gauges, widened by the shape prior's bias and by the volume in partly filled voxels
    (:data:`PARTIAL_VOLUME_GAIN`); an undetermined one is kept at ``initial``."""
    if sigma is None:
        sigma = float(np.sqrt(np.mean(model.residual(state, occupancy, 1.0) ** 2))) or 1.0
    profile = identifiability(model, occupancy, state, ("cross_section_mm2",), sigma)
    section = profile.estimates["cross_section_mm2"]
    se = profile.standard_errors["cross_section_mm2"]
    cone = unmeasured_band_deg(model.measurement(state).directions)
    model_error = math.hypot(SELF_SECTION_FLOOR, PARTIAL_VOLUME_GAIN * partial,
                             CONE_SECTION_ERROR_PER_DEG * cone if cone > MISSING_CONE_DEG else 0.0)
    low = section - 1.645 * se
    if cone > MISSING_CONE_DEG:  # there the partly filled voxels are the cone's blur as much as thin parts:
        low = min(low, section * (1.0 - self_section_bias(partial)))  # the uncorrected section stays in
    _record(report, "cross_section_mm2", section, (low, section + 1.645 * se), se, model_error * section)
    report.correlations["cross_section_mm2"] = profile.correlations["cross_section_mm2"]
    report.residual_rms, report.sigma_mm3, report.dip_offsets_mm = \
        profile.residual_rms, profile.sigma_mm3, profile.dip_offsets_mm
    cone_note = (f"; with a missing cone of {cone:.0f} deg, by {CONE_SECTION_ERROR_PER_DEG * cone:.0%} for the shape's "
                 "spread into the cone and down to the section without the bias correction")\
        if cone > MISSING_CONE_DEG else ""
    report.caveats["cross_section_mm2"] = (
        f"estimated through the shape prior (a nearly binary shape cannot be denser than 1), its interval widened by "
        f"{model_error:.1%} for the prior's bias ({partial:.0%} of the shape's volume in partly filled voxels"
        f"{cone_note}); at the configured step scale ({initial.step_scale:g}): with a true step scale s times the "
        "configured one "
        "the scene is 1/s times its true size and the true section s^3 times this one; for the section and the "
        "step scale, calibrate with a reference object")
    low, high = report.intervals["cross_section_mm2"]
    too_wide = (f"its 90% interval is +-{(high - low) / 2 / section:.1%}, "
                f"wider than {TOLERANCE['cross_section_mm2']:.0%}: "
                f"{partial:.0%} of the shape's volume sits in partly filled voxels (thin parts the grid does not "
                "resolve), whose density the gain trades against" +
                (f", and no dip reaches the {cone:.0f} deg about the horizontal plane, into which the shape prior "
                 "spreads the shape" if cone > MISSING_CONE_DEG else "") + "; a finer grid or a reference object")
    why = implausible or profile.undetermined.get("cross_section_mm2") or \
        (too_wide if (high - low) / 2 > TOLERANCE["cross_section_mm2"] * section else None)
    if why:
        state = replace(state, geometry=state.geometry.with_values(cross_section_mm2=initial.cross_section_mm2))
        report.undetermined["cross_section_mm2"] = why
        report.estimates["cross_section_mm2"] = _get(state, "cross_section_mm2", model.nominal_area)
        report.intervals.pop("cross_section_mm2")
        report.caveats.pop("cross_section_mm2")  # "estimated through the shape prior, its interval widened": not so
        report.shape_motion["cross_section_mm2"] = SHAPE_MOTION["cross_section_mm2"]
    return state


#: The default ``max_section_change`` (relative) for a scan with (True) and without (False) a missing cone wider
#: than :data:`MISSING_CONE_DEG` (:func:`self_calibrate`).
MAX_SECTION_CHANGE = {True: 0.2, False: 0.5}
#: An :func:`interior_density` below this: the joint step's shape is diluted (a section configured too small).
DILUTION_LIMIT = 0.95
#: The least :func:`interior_share` at which a joint step's shape is judged for a dilution. Below it the shape has no
#: interior the grid resolves, and its densest voxels are partly filled thin parts: the hammer at 32^3 (123 dips,
#: a section configured 5 % too large) settled at 0.88 with no voxel deep inside, was read as diluted, and its section
#: rescaled 25 % up came out 37 % too large with an interval of +-9.6 % (the bunny, part_B13 and spot hold 0.43-0.49 of
#: their fields' volume there at 32^3, a ball of 7.5 voxels' radius 0.69).
MIN_INTERIOR_SHARE = 0.1
#: How far (relative) past the dilution a diluted round rescales the section, so that the next round sees
#: volumes too large for a solid shape.
DILUTION_MARGIN = 0.1
#: A scan whose directions leave a cone wider than this (deg) unmeasured: its partly filled voxels are not all
#: thin parts, so the section's bias correction (:func:`~dipnet.calibration.model.self_section_bias`) may
#: overshoot (the audit: the authors' 0-35 deg tilts, sections 6-9 % high) and the interval keeps the
#: uncorrected section.
MISSING_CONE_DEG = 10.0
#: The section's model error (relative, 90 % half-width) per degree of an unmeasured band wider than
#: :data:`MISSING_CONE_DEG`: the shape prior decides how far the shape spreads into the band, and so its volume.
#: A ball (``shape.name=ball``, 24^3, 20-30 dips, true section 60000 mm^2) came out 3.6, 6.4, 12.4 and 17.5 %
#: high with bands of 15, 25, 40 and 55 deg (0.24-0.32 % per degree); a 25 mm ball (24^3, 16 dips) 4.7 % low with
#: a 25 deg band; every interval missed the truth. Added in quadrature to the partial-volume term, it names the
#: section undetermined from a band of about 30 deg on (wider than its 10 % tolerance).
CONE_SECTION_ERROR_PER_DEG = 0.0033


def section_change_limit(directions: torch.Tensor, max_section_change: float | None = None) -> float:
    """The relative change of the cross-section beyond which self-calibration keeps the configured one:
    ``max_section_change`` if given, else :data:`MAX_SECTION_CHANGE` for the missing cone of ``directions``
    ``(K, 3)`` (:func:`~dipnet.core.orientations.unmeasured_band_deg`)."""
    if max_section_change is not None:
        return float(max_section_change)
    return MAX_SECTION_CHANGE[unmeasured_band_deg(directions) > MISSING_CONE_DEG]


def _with_gain(solver):
    """A copy of ``solver`` that fits a volume gain with the shape (:class:`~dipnet.solvers.optimize.DataTerm`).

    Its ``"auto"`` prior weights are fixed at the weight rule's start (TV 1e-3): the section's bias correction
    (:func:`~dipnet.calibration.model.self_section_bias`) was measured at that weight, and a weight chosen from
    the data would trade the gain against the residual the rule aims at."""
    if not hasattr(solver, "fit_gain"):
        raise CalibrationError(f"the cross-section is estimated with the shape, which needs an optimisation solver "
                               f"(voxel, implicit); {type(solver).__name__} cannot fit it: drop cross_section_mm2 "
                               "from the parameters or calibrate it with a reference object (scripts/calibrate.py)")
    gained = copy.copy(solver)
    gained.fit_gain = True
    if getattr(solver, "weight_rule", None) is not None:
        gained.priors = with_weight(solver.priors, solver.weight_rule.start)
    return gained


def _shape_volume(recon: Reconstruction, shape: str) -> torch.Tensor:
    if shape == "binary":
        return torch.from_numpy(recon.binary.astype(np.float64))
    return recon.occupancy.detach().to(torch.float64).clamp(0.0, 1.0)
