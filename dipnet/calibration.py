"""Rig calibration: estimate a :class:`~dipnet.rig.geometry.RigGeometry` from dips.

Calibration is an estimation problem like reconstruction, and reuses its parts (the readers'
readings -> slabs map, the dip operator, any solver). It runs in two stages, the first of
which needs no grid and no shape, so nothing that depends on the geometry (the grid's
working ball, validation, a solver's support hull) sees the data before the geometry is
estimated:

1. **Moments** (:mod:`dipnet.calibration_moments`): the level drift from the rest level of
   every dip, then the pivot, tilt-axis offset, tilt zero (and for a reference object the
   step scale and spin zero) from the first two moments of every dip, which a rigid object
   fixes whatever its shape. A grid search over the angles and the step scale comes first,
   the heights are solved in closed form, so start heights 50+ mm off are no trap. 90%
   intervals from a bootstrap over dips (model error included), widened by a floor
   (:data:`MODEL_FLOOR`) measured over the random rigs of ``scripts/bench_calibration.py``.
2. **Volume**: a reference object's known volume gives the cross-section directly; without
   one (:func:`self_calibrate`) it is fitted as one volume gain jointly with the shape (the
   solver's ``fit_gain``), its interval widened by the shape prior's bias.

What cannot be estimated is named with the reason and how far the shape could move
(:attr:`CalibrationReport.undetermined`, :attr:`CalibrationReport.shape_motion`) and kept at
its configured value: for an unknown object the spin zero (the object's own rotation) and the
step scale (the scale of the whole scene; only section / step_scale^3 is fixed); for a
centred ball the spin zero (its symmetry) and, with pivot and offset near 0, the tilt zero.
The sensor lag is never estimated: at the simulator's 2 s settle time a lag shifts every
profile alike, which the pivot absorbs.
"""

from __future__ import annotations

import copy
import logging
import math
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np
import scipy.optimize
import scipy.sparse
import torch

from dipnet.calibration_moments import GAUGE_REASONS, TOLERANCE, KnownObject, fit_drift, fit_moments, dip_moments
from dipnet.grid import Grid
from dipnet.measurement import DipMeasurement
from dipnet.operators import make_operator
from dipnet.preprocess import preprocess
from dipnet.rawscan import RawScan
from dipnet.reconstruction import Reconstruction
from dipnet.rig.calibration_file import Calibration
from dipnet.rig.geometry import RigGeometry, invert_scan

log = logging.getLogger(__name__)

# estimable parameters: finite-difference step / natural scale (cross-section: relative)
PARAMETERS: dict[str, float] = {
    "pivot_mm": 1.0, "tilt_axis_offset_mm": 1.0, "tilt_zero_deg": 0.1, "spin_zero_deg": 0.1,
    "step_scale": 1e-3, "cross_section_mm2": 1e-3, "level_drift_mm_per_s": 1e-5, "t0_mm": 0.5,
}
#: Half-widths added (in quadrature) to every 90% interval, per method: model error the bootstrap over dips
#: does not see (the moments' discretisation, the sensor lag's shift, which a known centroid pushes into the
#: offset and tilt zero; relative for the section). Each is the floor that brings 90 % of the errors inside
#: their interval over 20-24 random rigs of the benchmark's range drawn with another seed (7) than the
#: benchmark's own (2026): self-calibration (4 meshes) errors at the 90th percentile 0.017 mm pivot, 0.028 mm
#: offset, 0.039 deg tilt zero; a 30 mm reference ball 0.053 mm, 0.39 mm, 0.38 deg, step scale 0.00078,
#: section 0.02 %, drift 2.8e-8 mm/s.
MODEL_FLOOR: dict[str, dict[str, float]] = {
    "self": {"pivot_mm": 0.02, "tilt_axis_offset_mm": 0.02, "tilt_zero_deg": 0.02, "level_drift_mm_per_s": 3e-8},
    "reference": {"pivot_mm": 0.06, "tilt_axis_offset_mm": 0.4, "tilt_zero_deg": 0.4, "spin_zero_deg": 0.4,
                  "step_scale": 0.0008, "cross_section_mm2": 0.0003, "level_drift_mm_per_s": 3e-8},
}
SELF_SECTION_FLOOR = 0.025  # the shape prior's bias on a self-calibrated section (relative), bench_calibration
#: The self-calibrated section's relative half-width also grows by this x the share of the shape's volume in
#: partly filled voxels (occupancy 0.1-0.9): thin parts the grid does not resolve let the gain trade against
#: their density (32^3, true rig geometry: hammer 85 % partial, section -8.8 %; bunny, spot, part_B13 16-18 %,
#: -1.6 % to -3.1 %).
PARTIAL_VOLUME_GAIN = 0.12
DEFAULT_SELF = ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale",
                "cross_section_mm2", "level_drift_mm_per_s")
DEFAULT_REFERENCE = DEFAULT_SELF
NOT_ESTIMATED = {"sensor_lag_s": "not estimated: at these settle times a lag shifts every profile alike, which "
                                 "the pivot absorbs; the configured value is used"}
GAUGES: dict[str, str] = {
    "shift_x_mm": "the object's position along x", "shift_y_mm": "the object's position along y",
    "shift_z_mm": "the object's position along the spin axis", "rot_x_deg": "the object's rotation about x",
    "rot_y_deg": "the object's rotation about y", "rot_z_deg": "the object's rotation about the spin axis",
    "dilate_mm": "the object's surface moving outward: a fatter or thinner object",
}


class CalibrationError(ValueError):
    """Calibration cannot give a trustworthy geometry (the message names the parameter or cause)."""


@dataclass
class CalibrationReport:
    """What the data determine.

    Attributes:
        estimates: parameter -> value (cross-section in mm^2); an undetermined one holds the
            configured value it was kept at.
        standard_errors: parameter -> standard error (same units): the bootstrap's for the moment
            stage, the Gauss-Newton one for the section of self-calibration (gauges included).
        intervals: parameter -> 90% interval ``(low, high)``, model-error floor included
            (module docstring); only for estimated parameters.
        correlations: parameter -> {other: correlation}.
        undetermined: parameter -> reason, for those the data do not pin to their tolerance.
        shape_motion: undetermined parameter -> how far the shape could move because of it.
        not_estimated: geometry field -> why it is not estimated (configured value used).
        residual_rms: RMS of the whitened profile residual of the volume stage (about 1 when the
            model explains the data to the noise level ``sigma_mm3``); NaN without one.
        sigma_mm3: the noise scale used to whiten the residual (mm^3 per slab).
        moment_rms: RMS misfit of the first (mm) and second (mm^2) moments at the estimate.
        dip_offsets_mm: the per-dip height offsets (mm), if estimated.
        caveats: parameter -> what its interval does not cover.
        method: ``"reference"`` or ``"self"``.
    """

    estimates: dict[str, float]
    standard_errors: dict[str, float]
    correlations: dict[str, dict[str, float]]
    undetermined: dict[str, str] = field(default_factory=dict)
    residual_rms: float = float("nan")
    sigma_mm3: float = float("nan")
    dip_offsets_mm: list[float] | None = None
    caveats: dict[str, str] = field(default_factory=dict)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    shape_motion: dict[str, str] = field(default_factory=dict)
    not_estimated: dict[str, str] = field(default_factory=lambda: dict(NOT_ESTIMATED))
    moment_rms: tuple[float, float] = (float("nan"), float("nan"))
    method: str = "self"

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "estimates": self.estimates, "standard_errors": self.standard_errors,
                "intervals_90": {k: list(v) for k, v in self.intervals.items()},
                "correlations": self.correlations, "undetermined": self.undetermined,
                "shape_motion": self.shape_motion, "not_estimated": self.not_estimated, "caveats": self.caveats,
                "residual_rms": self.residual_rms, "sigma_mm3": self.sigma_mm3, "moment_rms": list(self.moment_rms),
                "dip_offsets_mm": self.dip_offsets_mm}

    @property
    def determined(self) -> list[str]:
        """The estimated parameters the data determine (with an interval)."""
        return [n for n in self.estimates if n not in self.undetermined and n in self.intervals]

    def table(self) -> str:
        """A plain-text table: parameter, estimate, 90% interval, determined?"""
        lines = [f"{'parameter':<22} {'estimate':>12} {'90% interval':>25}  determined"]
        for name, value in self.estimates.items():
            low, high = self.intervals.get(name, (float("nan"), float("nan")))
            why = self.undetermined.get(name)
            status = f"no, kept at the configured value: {why}" if why else "yes"
            lines.append(f"{name:<22} {value:12.6g} {f'[{low:.6g}, {high:.6g}]':>25}  {status}")
        lines += [f"{name:<22} {'':>12} {'':>25}  {why}" for name, why in self.not_estimated.items()]
        return "\n".join(lines)


@dataclass
class State:
    """A point of the estimation: the geometry, a common start-height offset and per-dip offsets (mm)."""

    geometry: RigGeometry
    t0_mm: float = 0.0
    dip_offsets_mm: np.ndarray | None = None


class ProfileModel:
    """Readings -> slabs for a trial geometry, and the operator's profiles of a shape along its directions.

    Args:
        raw: the raw scan (commanded angles and stage, readings).
        grid, n_slabs: the reconstruction grid and slabs (default ``grid.n``).
        operator_factory: ``(grid, directions, n_slabs) -> DipOperator`` (default
            :func:`~dipnet.operators.make_operator`, auto backend).
        smooth: the paper's 5-tap smoothing in preprocessing.
        finish: applied to every preprocessed measurement (e.g. the readers' symmetry expansion).
    """

    def __init__(self, raw: RawScan, grid: Grid, n_slabs: int | None = None,
                 operator_factory: Callable | None = None, smooth: bool = False, finish: Callable[[DipMeasurement], DipMeasurement] | None = None) -> None:
        self.raw, self.grid, self.finish = raw, grid, finish
        self.n_slabs = grid.n if n_slabs is None else int(n_slabs)
        self.operator_factory, self.smooth = operator_factory or make_operator, smooth
        self.nominal_area = float(raw.header.tank_cross_section_mm2 or 0.0)
        self._operators: dict[bytes, Any] = {}

    def measurement(self, state: State, gauge: dict[str, float] | None = None, finish: bool = True) -> DipMeasurement:
        """The measurement the readers would make with ``state``; ``gauge`` moves / turns the object;
        ``finish=False`` skips :attr:`finish` (the measured dips only)."""
        inverted = invert_scan(self.raw, state.geometry)
        gauge = gauge or {}
        shift = np.array([gauge.get(k, 0.0) for k in ("shift_x_mm", "shift_y_mm", "shift_z_mm")])
        turn = _rotation(np.radians([gauge.get(k, 0.0) for k in ("rot_x_deg", "rot_y_deg", "rot_z_deg")]))
        for k, o in enumerate(inverted.orientations):
            extra = state.t0_mm + (0.0 if state.dip_offsets_mm is None else float(state.dip_offsets_mm[k]))
            direction = turn @ o.unit_direction
            o.direction = direction
            o.meta["t_start_mm"] = float(o.meta.get("t_start_mm", inverted.header.t_start_mm)) + extra \
                + float(shift @ direction)
        m = preprocess(inverted, grid=self.grid, n_slabs=self.n_slabs, t_start="metadata", smooth=self.smooth)
        return m if self.finish is None or not finish else self.finish(m)

    def operator(self, directions: torch.Tensor):
        key = np.round(directions.numpy(), 12).tobytes()
        if key not in self._operators:
            if len(self._operators) > 64:
                self._operators.clear()
            self._operators[key] = self.operator_factory(self.grid, directions, self.n_slabs)
        return self._operators[key]

    def residual(self, state: State, occupancy: torch.Tensor, sigma: float,
                 gauge: dict[str, float] | None = None) -> np.ndarray:
        """Whitened residual ``(A f - m) / sigma``, ``(K * M,)``."""
        m = self.measurement(state, gauge)
        with torch.no_grad():
            predicted = self.operator(m.directions)(occupancy)
        return ((predicted - m.profiles) / sigma).reshape(-1).numpy()


def _rotation(angles: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` for small rotation angles (rad) about x, y, z (Rodrigues)."""
    theta = float(np.linalg.norm(angles))
    if theta == 0.0:
        return np.eye(3)
    k = angles / theta
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * cross + (1 - math.cos(theta)) * cross @ cross


# ---------------------------------------------------------------------------- parameter vectors
def _get(state: State, name: str, area: float) -> float:
    if name == "t0_mm":
        return state.t0_mm
    if name == "cross_section_mm2":
        return state.geometry.area(area)
    return float(getattr(state.geometry, name))


def _with(state: State, values: dict[str, float]) -> State:
    t0 = values.pop("t0_mm", state.t0_mm)
    return replace(state, geometry=state.geometry.with_values(**values) if values else state.geometry, t0_mm=t0)


def _scales(params, area: float) -> np.ndarray:
    return np.array([PARAMETERS[p] * (area if p == "cross_section_mm2" else 1.0) for p in params])


def _check_params(params) -> tuple[str, ...]:
    params = tuple(params)
    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise CalibrationError(f"unknown or no calibration parameter(s) {unknown}; choose from {list(PARAMETERS)}")
    return params


# ---------------------------------------------------------------------------- geometry step
def fit_geometry(model: ProfileModel, occupancy: torch.Tensor, state: State, params, *,
                 dip_offset_sigma_mm: float | None = None, sigma: float | None = None,
                 max_nfev: int = 30) -> tuple[State, float]:
    """Least-squares geometry step; returns ``(state, noise scale sigma)``.

    The residual is the profile residual of the shape ``occupancy`` (``sigma`` in mm^3 per slab
    whitens it; default the RMS residual at ``state``). With ``dip_offset_sigma_mm`` every dip
    also gets a height offset with that Gaussian prior.
    """
    params = _check_params(params)
    area = model.nominal_area
    k = len(model.raw.orientations)
    if sigma is None:
        sigma = float(np.sqrt(np.mean(model.residual(state, occupancy, 1.0) ** 2))) or 1.0
    noise = sigma

    def residual(trial: State, gauge=None) -> np.ndarray:
        return model.residual(trial, occupancy, noise, gauge)
    scales = _scales(params, area)
    per_dip = dip_offset_sigma_mm is not None
    x0 = np.array([_get(state, p, area) for p in params]) / scales
    offsets0 = np.zeros(k) if state.dip_offsets_mm is None else np.asarray(state.dip_offsets_mm, dtype=float)

    def unpack(x: np.ndarray) -> State:
        s = _with(state, dict(zip(params, x[: len(params)] * scales)))
        return replace(s, dip_offsets_mm=x[len(params):] if per_dip else state.dip_offsets_mm)

    def fun(x: np.ndarray) -> np.ndarray:
        try:
            r = residual(unpack(x))
        except ValueError as exc:  # an unphysical trial geometry: a large, finite residual
            log.debug("trial geometry rejected: %s", exc)
            r = np.full(rows, 1e3)
        return np.concatenate([r, x[len(params):] / dip_offset_sigma_mm]) if per_dip else r

    x_start = np.concatenate([x0, offsets0]) if per_dip else x0
    rows = residual(state).size
    sparsity = None
    if per_dip:
        m = model.n_slabs
        sparsity = scipy.sparse.lil_matrix((k * m + k, len(params) + k), dtype=int)
        sparsity[: k * m, : len(params)] = 1
        for j in range(k):
            sparsity[j * m:(j + 1) * m, len(params) + j] = 1
            sparsity[k * m + j, len(params) + j] = 1
    result = scipy.optimize.least_squares(fun, x_start, method="trf", diff_step=1e-3 / np.maximum(np.abs(x_start), 1),
                                          jac_sparsity=sparsity, max_nfev=max_nfev, x_scale=1.0, xtol=1e-5, ftol=1e-6)
    if not np.all(np.isfinite(result.x)):
        raise CalibrationError("the geometry step did not converge (non-finite parameters)")
    return unpack(result.x), sigma


def identifiability(model: ProfileModel, occupancy: torch.Tensor, state: State, params, sigma: float = 1.0,
                    gauges: bool = True) -> CalibrationReport:
    """Standard errors and correlations of ``params`` at ``state`` from the Gauss-Newton Hessian of
    the profile residual of the shape ``occupancy``; with ``gauges`` the shape's own translations,
    rotations and dilation are nuisance parameters (:data:`GAUGES`). Names the parameters whose
    standard error exceeds their tolerance and their most correlated partner."""
    params = _check_params(params)
    area = model.nominal_area
    surface = _surface_density(occupancy, model.grid)

    def residual(trial: State, gauge=None) -> np.ndarray:
        gauge = dict(gauge or {})
        return model.residual(trial, occupancy + gauge.pop("dilate_mm", 0.0) * surface, sigma, gauge)
    names = list(params) + (list(GAUGES) if gauges else [])
    base = residual(state)
    columns, kept = [], []
    for name in names:
        if name in GAUGES:
            h = 0.2 if name.startswith("rot") else 0.5 if name.startswith("shift") else 0.1 * model.grid.voxel_size
            plus, minus = residual(state, {name: h}), residual(state, {name: -h})
        else:
            h = float(_scales([name], area)[0])
            value = _get(state, name, area)
            plus = residual(_with(state, {name: value + h}))
            minus = residual(_with(state, {name: value - h}))
        if plus.shape != base.shape or minus.shape != base.shape:  # symmetry images merged differently
            if name in GAUGES:
                log.info("identifiability: gauge %s changes the symmetry-expanded directions; left out", name)
                continue
            raise CalibrationError(f"{name} changes which symmetry images coincide: calibrate it without "
                                   "the symmetry expansion")
        columns.append((plus - minus) / (2 * h))
        kept.append(name)
    names = kept
    jac = np.stack(columns, axis=1)
    dof = max(1, base.size - len(names))
    s2 = float(base @ base) / dof
    norms = np.linalg.norm(jac, axis=0)
    flat = norms <= 1e-6 * max(float(norms.max()), 1e-300)  # the data do not depend on these at all
    hessian = jac.T @ jac + np.diag(np.where(flat, 1.0, 0.0)) + 1e-12 * np.trace(jac.T @ jac) * np.eye(len(names))
    cov = s2 * np.linalg.inv(hessian)
    se = np.where(flat, np.inf, np.sqrt(np.maximum(np.diag(cov), 0.0)))
    spread = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.maximum(np.outer(spread, spread), 1e-300)
    report = CalibrationReport(
        estimates={p: _get(state, p, area) for p in params},
        standard_errors={n: float(s) for n, s in zip(names, se)},
        correlations={n: {o: float(corr[i, j]) for j, o in enumerate(names) if j != i} for i, n in enumerate(names)},
        residual_rms=float(np.sqrt(s2)), sigma_mm3=sigma,
        dip_offsets_mm=None if state.dip_offsets_mm is None else [float(x) for x in state.dip_offsets_mm])
    for i, name in enumerate(params):
        tol = TOLERANCE[name] * (report.estimates[name] if name == "cross_section_mm2" else 1.0)  # relative
        if flat[i]:
            report.undetermined[name] = ("the data do not depend on it: the object's own rotation or position "
                                         "absorbs it completely")
        elif not se[i] <= tol:
            j = max((j for j in range(len(names)) if j != i), key=lambda j: abs(corr[i, j]), default=None)
            partner = "" if j is None else \
                f"; degenerate with {names[j]} ({GAUGES.get(names[j], 'a rig parameter')}, correlation {corr[i, j]:+.3f})"
            report.undetermined[name] = f"standard error {se[i]:.3g} > {tol:.3g}{partner}"
    return report


def _surface_density(occupancy: torch.Tensor, grid: Grid) -> torch.Tensor:
    """``|grad f|`` (1/mm, central differences): moving the surface of ``f`` outward by ``d`` mm adds
    about ``d |grad f|`` to the occupancy (the dilation gauge)."""
    f = occupancy.detach().numpy()
    gradient = np.gradient(f, grid.voxel_size)
    return torch.from_numpy(np.sqrt(sum(g**2 for g in gradient)))


def _warn_undetermined(report: CalibrationReport, what: str) -> None:
    messages = [f"{what}: {name} is not determined by these dips, kept at {report.estimates[name]:.6g} ({why}); "
                f"if it is wrong: {report.shape_motion.get(name, 'see the report')}"
                for name, why in report.undetermined.items()]
    messages += [f"{what}: {name} {why}" for name, why in report.caveats.items()]
    for message in messages:
        log.warning(message)
        warnings.warn(message, stacklevel=3)


def to_calibration(geometry: RigGeometry, report: CalibrationReport, rig: str, tank: str, notes: str = "") -> Calibration:
    """The calibration file's record of a result: estimates with their intervals; every other field
    listed under ``not_estimated`` with the reason (never a configured value labelled an estimate)."""
    fields = [f for f in geometry.to_dict() if f != "cross_section_mm2" or geometry.cross_section_mm2 is not None
              or f in report.undetermined]
    not_estimated = {f: "not determined by the dips, configured value kept: " + report.undetermined[f]
                     for f in fields if f in report.undetermined}
    not_estimated.update({f: why for f, why in report.not_estimated.items() if f in fields})
    not_estimated.update({f: "not estimated: not among the calibrated parameters, configured value kept"
                          for f in fields if f not in report.estimates and f not in not_estimated})
    determined = [f for f in report.determined if f in fields]
    return Calibration(geometry, rig=rig, tank=tank, method=report.method,
                       uncertainty={f: report.standard_errors[f] for f in determined},
                       intervals={f: report.intervals[f] for f in determined}, not_estimated=not_estimated,
                       notes=notes)


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


def _moment_stage(raw: RawScan, params, initial: RigGeometry, kind: str, known: KnownObject | None,
                  seed: int = 0) -> tuple[State, CalibrationReport]:
    """Stage 1 (module docstring): the drift, then the heights and angles from the dips' moments.

    ``kind`` is ``"self"`` (unknown object: spin zero and step scale are gauges, never fitted) or
    ``"reference"`` (``known`` moments). Undetermined parameters are refitted at their configured value.
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
    moments = dip_moments(raw, geometry)
    if kind == "self":
        gauges = {p: GAUGE_REASONS[(kind, p)] for p in ("spin_zero_deg", "step_scale") if p in params}
    else:  # a reference object centred on the spin axis looks alike at every spin
        on_axis = float(np.hypot(*known.centroid[:2])) < 1e-6 and np.allclose(known.covariance[0, 0],
                                                                             known.covariance[1, 1])
        gauges = {"spin_zero_deg": GAUGE_REASONS[(kind, "spin_zero_deg")]} if on_axis and "spin_zero_deg" in params \
            else {}
    free = tuple(p for p in params if p in ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg",
                                            "step_scale") and p not in gauges)
    fixed = {f: float(getattr(initial, f)) for f in ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg",
                                                     "spin_zero_deg", "step_scale")}
    fit = fit_moments(moments, free, known=known, fixed=fixed, seed=seed) if free else None
    undetermined = dict(gauges)
    if fit is not None:
        undetermined.update(fit.undetermined(kind))
        kept = tuple(p for p in free if p not in undetermined)
        if kept != free:
            fit = fit_moments(moments, kept, known=known, fixed=fixed, seed=seed) if kept else None
        if fit is not None:
            geometry = geometry.with_values(**{p: fit.values[p] for p in fit.free})
            report.moment_rms = fit.residual_rms
            floors = dict(MODEL_FLOOR[kind])
            if known is not None:  # the midpoint rule misses h^2 / 12 of every dip's variance (h: the stage step)
                step = float(np.median(np.concatenate([np.diff(o.stage_mm) for o in raw.orientations])))
                floors["step_scale"] = math.hypot(floors["step_scale"],
                                                  step**2 / 12.0 / np.trace(known.covariance) * 3.0)
            for p in fit.free:
                _record(report, p, fit.values[p], fit.intervals[p], fit.bootstrap_sd[p], floors[p])
            report.correlations.update(fit.correlations)
    radius = _object_radius(fit, known)
    undetermined.update(report.undetermined)
    for p, why in undetermined.items():
        report.estimates[p] = float(getattr(initial, p))
        report.undetermined[p] = why
        report.shape_motion[p] = SHAPE_MOTION[p].format(arc=np.radians(radius), pct=0.01 * radius)
    return State(geometry), report


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


# ---------------------------------------------------------------------------- reference object
def calibrate_reference(raw: RawScan, shape, grid: Grid, params=DEFAULT_REFERENCE, *, initial: RigGeometry | None = None,
                        n_slabs: int | None = None, operator_factory: Callable | None = None, supersample: int = 3,
                        max_relative_residual: float = 0.05, seed: int = 0) -> tuple[RigGeometry, CalibrationReport]:
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
            object does not fit: wrong size, wrong pose, or the data are not of this object).

    Returns ``(geometry, report)``. Raises :class:`CalibrationError` when the object does not fit.
    """
    params = _check_params(params)
    initial = initial or RigGeometry()
    known = known_object(shape)
    state, report = _moment_stage(raw, params, initial, "reference", known, seed)
    if "cross_section_mm2" in params:
        moments = dip_moments(raw, state.geometry)
        rng = np.random.default_rng(seed)
        rises = np.asarray(moments.rise)  # mm of level per dip, drift removed
        section = known.volume / rises.mean() if raw.header.quantity == "level_mm" else None
        if section is not None:
            draws = [known.volume / rises[rng.integers(0, len(rises), len(rises))].mean() for _ in range(200)]
            state = replace(state, geometry=state.geometry.with_values(cross_section_mm2=float(section)))
            _record(report, "cross_section_mm2", float(section), tuple(np.percentile(draws, [5, 95])),
                    float(np.std(draws)), MODEL_FLOOR["reference"]["cross_section_mm2"] * section)
    model = ProfileModel(raw, grid, n_slabs, operator_factory)
    occupancy = shape.occupancy(grid, supersample=supersample).to(torch.float64)
    measured = model.measurement(state).profiles.numpy().reshape(-1)
    fit = float(np.linalg.norm(model.residual(state, occupancy, 1.0)) / max(np.linalg.norm(measured), 1e-300))
    if fit > max_relative_residual:
        raise CalibrationError(f"the reference object does not fit the dips: relative profile residual {fit:.3f} "
                               f"> {max_relative_residual} at the calibrated geometry; check its size, pose and "
                               "the recording")
    report.residual_rms = fit
    _warn_undetermined(report, "reference calibration")
    return state.geometry, report


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


def self_calibrate(raw: RawScan, grid: Grid, solver, params=DEFAULT_SELF, *, n_slabs: int | None = None,
                   operator_factory: Callable | None = None, smooth: bool = False, finish=None,
                   initial: RigGeometry | None = None, iterations: int = 1, dip_offset_sigma_mm: float | None = None,
                   shape: str = "binary", max_nfev: int = 20, gain_solver=None, max_section_change: float = 0.2,
                   seed: int = 0) -> SelfCalibration:
    """Estimate the rig geometry jointly with the shape.

    1. The moment stage (module docstring): drift, pivot, offset and tilt zero from the dips'
       first two moments, with no grid and no shape. The spin zero and the step scale are
       gauges of an unknown object: named, with how far the shape could move, and kept.
    2. The cross-section jointly with the shape: the shape step (``gain_solver`` or ``solver``
       with ``fit_gain``) fits one gain ``a`` on every predicted volume together with the shape;
       the calibrated cross-section is ``assumed / a``. Fitted jointly, the gain and the shape's
       size compete through the profiles' *shapes* (a dilated object widens every profile, a gain
       only scales it; a nearly binary interior cannot exceed 1). Its interval is widened by the
       shape prior's bias (:data:`SELF_SECTION_FLOOR`). With ``dip_offset_sigma_mm`` a geometry
       step then fits per-dip height offsets to that shape. ``iterations`` such rounds.
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
            not trusted: named undetermined and kept (the three cats, with a 56 deg missing cone:
            the gain came out 1.46, a section 31 % below the tank's).
        gain_solver: the solver of step 2 (default ``solver``); the final shape is ``solver``'s.
        seed: the bootstrap's.

    Returns:
        :class:`SelfCalibration` with the report of both stages.
    """
    if shape not in ("occupancy", "binary"):
        raise CalibrationError(f"shape must be 'occupancy' or 'binary', got {shape!r}")
    if not max_section_change > 0:
        raise CalibrationError(f"max_section_change must be positive (relative), got {max_section_change!r}")
    params = _check_params(params)
    initial = initial or RigGeometry()
    volume_params = ("cross_section_mm2",) if "cross_section_mm2" in params else ()
    shape_solver = _with_gain(gain_solver or solver) if volume_params else (gain_solver or solver)
    state, report = _moment_stage(raw, params, initial, "self", None, seed)
    model = ProfileModel(raw, grid, n_slabs, operator_factory, smooth, finish)
    history: list[dict] = [{"stage": "moments", **{p: _get(state, p, model.nominal_area) for p in params}}]
    sigma, implausible, occupancy, partial = None, None, None, 0.0
    for it in range(iterations if volume_params or dip_offset_sigma_mm is not None else 0):
        measurement = model.measurement(state)
        recon = shape_solver.solve(measurement, model.operator(measurement.directions))
        occupancy = _shape_volume(recon, shape)
        partial = partial_volume(recon)
        gain = float(recon.info.get("gain", 1.0))
        if volume_params and abs(1.0 / gain - 1.0) > max_section_change:
            implausible = (f"the joint shape step moved it by {1 / gain - 1:+.1%} (more than max_section_change "
                           f"{max_section_change:.0%}): the shape prior, not the data, decided the volume (e.g. a "
                           "missing cone leaves the object's density free)")
        elif volume_params:
            state = _with(state, {"cross_section_mm2": _get(state, "cross_section_mm2", model.nominal_area) / gain})
        if dip_offset_sigma_mm is not None:
            state, sigma = fit_geometry(model, occupancy, state, ("t0_mm",), dip_offset_sigma_mm=dip_offset_sigma_mm,
                                        sigma=sigma, max_nfev=max_nfev)
        history.append({"stage": f"shape {it}", "gain": gain, "partial_volume": partial,
                        **{p: _get(state, p, model.nominal_area) for p in params}})
    for row in history:
        log.info("self-calibration %s", ", ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}"
                                                  for k, v in row.items()))
    if volume_params:
        state = _section_report(report, model, state, occupancy, sigma, initial, implausible, partial)
    measurement = model.measurement(state)
    recon = solver.solve(measurement, model.operator(measurement.directions))
    _warn_undetermined(report, "self-calibration")
    measurement.metadata = {**measurement.metadata, "self_calibration": report.to_dict(),
                            "geometry": state.geometry.to_dict(), "t0_mm": state.t0_mm}
    recon.info = {**recon.info, "self_calibration": report.to_dict()}
    return SelfCalibration(state.geometry, state.t0_mm, measurement, recon, report, history)


def partial_volume(recon: Reconstruction) -> float:
    """Share of a reconstruction's volume in partly filled voxels (occupancy between 0.1 and 0.9)."""
    occ = recon.occupancy.detach().to(torch.float64)
    total = float(occ.sum())
    return float(occ[(occ > 0.1) & (occ < 0.9)].sum()) / total if total > 0 else 1.0


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
    model_error = math.hypot(SELF_SECTION_FLOOR, PARTIAL_VOLUME_GAIN * partial)
    _record(report, "cross_section_mm2", section, (section - 1.645 * se, section + 1.645 * se), se,
            model_error * section)
    report.correlations["cross_section_mm2"] = profile.correlations["cross_section_mm2"]
    report.residual_rms, report.sigma_mm3, report.dip_offsets_mm = \
        profile.residual_rms, profile.sigma_mm3, profile.dip_offsets_mm
    report.caveats["cross_section_mm2"] = (
        f"estimated through the shape prior (a nearly binary shape cannot be denser than 1), its interval widened by "
        f"{model_error:.1%} for the prior's bias ({partial:.0%} of the shape's volume in partly filled voxels); at "
        f"the configured step scale "
        f"({initial.step_scale:g}): a step-scale error moves it too; for a better section, "
        "calibrate with a reference object")
    low, high = report.intervals["cross_section_mm2"]
    too_wide = (f"its 90% interval is +-{(high - low) / 2 / section:.1%}, wider than {TOLERANCE['cross_section_mm2']:.0%}: "
                f"{partial:.0%} of the shape's volume sits in partly filled voxels (thin parts the grid does not "
                "resolve), whose density the gain trades against; a finer grid or a reference object")
    why = implausible or profile.undetermined.get("cross_section_mm2") or \
        (too_wide if (high - low) / 2 > TOLERANCE["cross_section_mm2"] * section else None)
    if why:
        state = replace(state, geometry=state.geometry.with_values(cross_section_mm2=initial.cross_section_mm2))
        report.undetermined["cross_section_mm2"] = why
        report.estimates["cross_section_mm2"] = _get(state, "cross_section_mm2", model.nominal_area)
        report.intervals.pop("cross_section_mm2")
        report.shape_motion["cross_section_mm2"] = SHAPE_MOTION["cross_section_mm2"]
    return state


def _with_gain(solver):
    """A copy of ``solver`` that fits a volume gain with the shape (:class:`~dipnet.solvers.optimize.DataTerm`)."""
    if not hasattr(solver, "fit_gain"):
        raise CalibrationError(f"the cross-section is estimated with the shape, which needs an optimisation solver "
                               f"(voxel, implicit); {type(solver).__name__} cannot fit it: drop cross_section_mm2 "
                               "from the parameters or calibrate it with a reference object (scripts/calibrate.py)")
    gained = copy.copy(solver)
    gained.fit_gain = True
    return gained


def _shape_volume(recon: Reconstruction, shape: str) -> torch.Tensor:
    if shape == "binary":
        return torch.from_numpy(recon.binary.astype(np.float64))
    return recon.occupancy.detach().to(torch.float64).clamp(0.0, 1.0)
