"""Rig calibration: estimate a :class:`~dipnet.rig.geometry.RigGeometry` from dips.

Calibration is an estimation problem like reconstruction, and reuses its parts:

* the readings -> slabs map is the readers' (:func:`~dipnet.rig.geometry.invert_scan` then
  :func:`~dipnet.preprocess.preprocess`), re-run for every trial geometry;
* the shape's profiles come from the dip operator (:func:`~dipnet.operators.make_operator`);
* the shape step of self-calibration is any :class:`~dipnet.solvers.Solver`.

The geometry step is nonlinear least squares (``scipy.optimize.least_squares``, finite
differences) on the profile residual ``r = (A(theta(g)) f - m(g)) / sigma`` with the shape
``f`` fixed, over the chosen :data:`PARAMETERS` (RigGeometry fields plus ``t0_mm``, a common
offset of every dip's start height) and optionally one height offset per dip (with a
Gaussian prior of ``dip_offset_sigma_mm``).

* :func:`calibrate_reference`: a reference object of known shape and pose (a ball or a
  cylinder of known size) -> one geometry step with ``f`` = its occupancy;
* :func:`self_calibrate`: shape unknown -> heights and directions from the shape-free moment
  residual, the cross-section as a volume gain fitted with the shape (the solver's
  ``fit_gain``), per-dip offsets by a geometry step on that shape, then a final shape step.

What the data determine (:func:`identifiability`): from the Gauss-Newton Hessian ``J^T J`` of
the data term at the estimate, standard errors ``sqrt(diag(s^2 (J^T J)^-1))`` (``s^2`` the
residual variance) and correlations. For self-calibration ``J`` also holds the *gauge*
directions of the unknown shape: moving it (``shift_*_mm``: ``t_k += v . theta_k``),
turning it (``rot_*_deg``: the directions turn instead) or growing it (``dilate_mm``: the
surface moves outward, ``f += d |grad f|``), which the shape step can always absorb. A parameter whose standard error exceeds its tolerance (:data:`TOLERANCE`) is not
identifiable from the plan; the partner it is most correlated with is named (e.g. the spin
zero offset is the object's own rotation about the spin axis; the pivot with a free ``t0_mm``
is the object's position along the spin axis). Self-calibration warns and keeps such
parameters at their initial values; reference calibration refuses (``CalibrationError``).

The cross-section is identifiable only because the solver's shape is (nearly) binary: the
data alone cannot tell a larger tank from a denser object. It is fitted as one volume gain
jointly with the shape (:func:`self_calibrate`).
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

from dipnet.grid import Grid
from dipnet.measurement import DipMeasurement
from dipnet.operators import make_operator
from dipnet.preprocess import preprocess
from dipnet.rawscan import RawScan
from dipnet.reconstruction import Reconstruction
from dipnet.rig.geometry import RigGeometry, invert_scan

log = logging.getLogger(__name__)

# estimable parameters: finite-difference step / natural scale (cross-section: relative)
PARAMETERS: dict[str, float] = {
    "pivot_mm": 1.0, "tilt_axis_offset_mm": 1.0, "tilt_zero_deg": 0.1, "spin_zero_deg": 0.1,
    "step_scale": 1e-3, "cross_section_mm2": 1e-3, "level_drift_mm_per_s": 1e-5, "t0_mm": 0.5,
}
# a parameter is "determined" when its standard error is below this (cross-section: relative)
TOLERANCE: dict[str, float] = {
    "pivot_mm": 2.5, "tilt_axis_offset_mm": 1.5, "tilt_zero_deg": 0.5, "spin_zero_deg": 0.5,
    "step_scale": 0.005, "cross_section_mm2": 0.005, "level_drift_mm_per_s": 5e-5, "t0_mm": 1.0,
}
GAUGES: dict[str, str] = {
    "shift_x_mm": "the object's position along x", "shift_y_mm": "the object's position along y",
    "shift_z_mm": "the object's position along the spin axis", "rot_x_deg": "the object's rotation about x",
    "rot_y_deg": "the object's rotation about y", "rot_z_deg": "the object's rotation about the spin axis",
    "dilate_mm": "the object's surface moving outward: a fatter or thinner object",
}
SECTION_BIAS_NOTE = "-1.3 % to +0.8 % with the implicit field, -2.4 % to +0.2 % with voxels, on 4 meshes"  # README
DEFAULT_SELF = ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "cross_section_mm2")


class CalibrationError(ValueError):
    """Calibration cannot give a trustworthy geometry (the message names the parameter or cause)."""


@dataclass
class CalibrationReport:
    """What the data determine.

    Attributes:
        estimates: parameter -> value (cross-section in mm^2).
        standard_errors: parameter -> standard error (same units), gauges included for self-calibration.
        correlations: parameter -> {other: correlation}.
        undetermined: parameter -> reason (named partner), for those above :data:`TOLERANCE`.
        residual_rms: RMS of the whitened profile residual (about 1 when the model explains the data
            to the noise level; the noise scale is ``sigma_mm3``).
        sigma_mm3: the noise scale used to whiten the residual (mm^3 per slab).
        dip_offsets_mm: the per-dip height offsets (mm), if estimated.
        caveats: parameter -> what its standard error does not cover.
    """

    estimates: dict[str, float]
    standard_errors: dict[str, float]
    correlations: dict[str, dict[str, float]]
    undetermined: dict[str, str] = field(default_factory=dict)
    residual_rms: float = float("nan")
    sigma_mm3: float = float("nan")
    dip_offsets_mm: list[float] | None = None
    caveats: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"estimates": self.estimates, "standard_errors": self.standard_errors,
                "correlations": self.correlations, "undetermined": self.undetermined, "caveats": self.caveats,
                "residual_rms": self.residual_rms, "sigma_mm3": self.sigma_mm3, "dip_offsets_mm": self.dip_offsets_mm}

    def table(self) -> str:
        """A plain-text table: parameter, estimate, standard error, determined?"""
        lines = [f"{'parameter':<22} {'estimate':>12} {'std err':>10}  determined"]
        for name, value in self.estimates.items():
            se = self.standard_errors.get(name, float("nan"))
            why = self.undetermined.get(name)
            lines.append(f"{name:<22} {value:12.5g} {se:10.3g}  {'no: ' + why if why else 'yes'}")
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

    def moment_residual(self, state: State, gauge: dict[str, float] | None = None) -> np.ndarray:
        """Whitened residual of the Radon range conditions of the first two moments, ``(2 K,)``.

        The profile of a rigid object along ``theta`` has its centroid at ``c . theta`` and its
        mean squared height at ``theta^T S theta`` (``c``, ``S`` = the object's centroid and
        second-moment matrix over its volume), whatever the shape. ``c`` and ``S`` are fitted
        linearly; what is left measures how far the geometry is from making the dips one
        rigid object. Units: the first moments in 0.1 slab, the second in 0.1 slab x the grid radius.
        Only the measured dips count (no symmetry images or interpolated ones).
        """
        m = self.measurement(state, gauge, finish=False)
        edges = m.offsets[0].item() + m.slab_thickness * np.arange(m.n_slabs + 1)
        t = 0.5 * (edges[1:] + edges[:-1])
        p = m.profiles.numpy()
        volume = p.sum(1)
        if np.any(volume <= 0):
            raise ValueError("a dip holds no volume inside the grid")
        first, second = p @ t / volume, p @ t**2 / volume
        d = m.directions.numpy()
        quad = np.stack([d[:, 0]**2, d[:, 1]**2, d[:, 2]**2, 2 * d[:, 0] * d[:, 1], 2 * d[:, 0] * d[:, 2],
                         2 * d[:, 1] * d[:, 2]], axis=1)
        r1 = first - d @ np.linalg.lstsq(d, first, rcond=None)[0]
        r2 = second - quad @ np.linalg.lstsq(quad, second, rcond=None)[0]
        unit = 0.1 * m.slab_thickness
        return np.concatenate([r1 / unit, r2 / (unit * self.grid.radius)])

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
def fit_geometry(model: ProfileModel, occupancy: torch.Tensor | None, state: State, params, *,
                 dip_offset_sigma_mm: float | None = None, sigma: float | None = None,
                 max_nfev: int = 30) -> tuple[State, float]:
    """Least-squares geometry step; returns ``(state, noise scale sigma)``.

    With a shape ``occupancy`` the residual is the profile residual (``sigma`` in mm^3 per slab
    whitens it; default the RMS residual at ``state``); with ``occupancy=None`` it is the
    shape-free moment residual (:meth:`ProfileModel.moment_residual`). With
    ``dip_offset_sigma_mm`` every dip also gets a height offset with that Gaussian prior.
    """
    params = _check_params(params)
    area = model.nominal_area
    k = len(model.raw.orientations)
    if occupancy is None:
        residual = model.moment_residual
        sigma = 1.0
    else:
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
        if occupancy is None:
            raise CalibrationError("per-dip height offsets need a shape (they are free in the moment fit)")
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


def identifiability(model: ProfileModel, occupancy: torch.Tensor | None, state: State, params, sigma: float = 1.0,
                    gauges: bool = True) -> CalibrationReport:
    """Standard errors and correlations of ``params`` at ``state`` from the Gauss-Newton Hessian
    (module docstring); with ``gauges`` the shape's own translations and rotations are nuisance
    parameters (the moment residual, ``occupancy=None``, has them built in: its centroid and
    second moments are fitted). Names the undetermined parameters and their most correlated partner."""
    params = _check_params(params)
    area = model.nominal_area
    if occupancy is None:
        gauges = False

        def residual(trial: State, gauge=None) -> np.ndarray:
            return model.moment_residual(trial, gauge)
    else:
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
        tol = TOLERANCE[name] * (report.estimates[name] if name == "cross_section_mm2" else 1.0)
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
    messages = [f"{what}: {name} is not identifiable from this plan and shape ({why})"
                for name, why in report.undetermined.items()]
    messages += [f"{what}: {name} {why}" for name, why in report.caveats.items()]
    for message in messages:
        log.warning(message)
        warnings.warn(message, stacklevel=3)


# ---------------------------------------------------------------------------- reference object
def calibrate_reference(raw: RawScan, shape, grid: Grid, params=("pivot_mm", "tilt_axis_offset_mm",
                        "tilt_zero_deg", "cross_section_mm2"), *, initial: RigGeometry | None = None,
                        n_slabs: int | None = None, operator_factory: Callable | None = None, supersample: int = 3,
                        max_relative_residual: float = 0.05) -> tuple[RigGeometry, CalibrationReport]:
    """The rig geometry from dips of a reference object of known geometry and pose.

    Args:
        raw: the reference object's raw scan (a few orientations; tilted ones for the pivot and
            offset, several spins for the zero offsets).
        shape: the reference object (:class:`~dipnet.shapes.Shape`: e.g. ``Ball(30)``) in the
            object frame the rig holds it in.
        grid: the grid its occupancy is sampled on (fine enough that a voxel is << its size).
        n_slabs, operator_factory: slabs and operators (:class:`ProfileModel`).
        params: parameters to estimate (:data:`PARAMETERS`).
        initial: starting geometry (default the ideal rig).
        max_relative_residual: refuse when ``|A f - m| / |m|`` stays above this at the estimate (the
            object does not fit: wrong size, wrong pose, or the data are not of this object).

    Returns ``(geometry, report)``. Raises :class:`CalibrationError` naming undetermined
    parameters, or when the reference object does not fit the data.
    """
    model = ProfileModel(raw, grid, n_slabs, operator_factory)
    occupancy = shape.occupancy(grid, supersample=supersample).to(torch.float64)
    volume = float(shape.volume)
    sigma = max(volume / model.n_slabs * 1e-3, 1e-9)  # 0.1 % of a mean slab: residual_rms in those units
    state, _ = fit_geometry(model, occupancy, State(initial or RigGeometry()), params, sigma=sigma, max_nfev=50)
    measured = model.measurement(state).profiles.numpy().reshape(-1)
    fit = float(np.linalg.norm(model.residual(state, occupancy, 1.0)) / max(np.linalg.norm(measured), 1e-300))
    if fit > max_relative_residual:
        raise CalibrationError(f"the reference object does not fit the dips: relative profile residual {fit:.3f} "
                               f"> {max_relative_residual}; check its size, pose and the recording")
    report = identifiability(model, occupancy, state, params, sigma, gauges=False)
    if report.undetermined:
        raise CalibrationError("reference calibration cannot determine " + "; ".join(
            f"{n} ({why})" for n, why in report.undetermined.items()) + ": add tilted / spun dips or drop it")
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
                   operator_factory: Callable | None = None, smooth: bool = False, finish=None, initial: RigGeometry | None = None,
                   iterations: int = 1, dip_offset_sigma_mm: float | None = None, shape: str = "binary",
                   max_nfev: int = 20, gain_solver=None, max_section_change: float = 0.2) -> SelfCalibration:
    """Estimate the rig geometry jointly with the shape.

    1. Heights and directions (every parameter but the cross-section) from the shape-free
       moment residual (:meth:`ProfileModel.moment_residual`): the dips must be profiles of one
       rigid object. Parameters this cannot determine are reported and kept at ``initial``.
    2. The cross-section jointly with the shape: the shape step (``solver`` with ``fit_gain``)
       fits one gain ``a`` on every predicted volume together with the shape. A wrong
       cross-section multiplies every measured volume by ``a = assumed / true``, so the
       calibrated cross-section is ``assumed / a``. With ``dip_offset_sigma_mm`` a geometry step
       then fits the per-dip height offsets to that shape. ``iterations`` such rounds.
    3. A final shape step (no gain) with the calibrated geometry.

    Why a joint gain and not alternation: in alternation the shape step, at a fixed wrong
    cross-section, dilates or erodes the shape to absorb most of the error, so the next
    geometry step sees only a fraction of it (bunny, 64^3, -8 % section: 3.5-5.6 % left after
    two over-relaxed alternations). Fitted jointly, the gain and the shape's size compete
    through the profiles' *shapes*: a dilated object widens every profile, a gain only scales
    it, and the interior of a nearly binary shape cannot exceed 1. What remains is the bias
    of the shape prior (measured with ``scripts/bench_calibration.py``, see README).

    Args:
        raw: the object's raw scan (complete dips that start before contact and end under water).
        grid, n_slabs, operator_factory, smooth: reconstruction grid, slabs, operators, smoothing.
        finish: applied to every preprocessed measurement (:class:`ProfileModel`).
        solver: any :class:`~dipnet.solvers.Solver` (the shape step); the cross-section needs
            an optimisation solver (``fit_gain``: voxel, implicit).
        params: geometry parameters to estimate (:data:`PARAMETERS`).
        initial: starting geometry (default: the ideal rig).
        iterations: rounds of step 2.
        dip_offset_sigma_mm: also estimate one height offset per dip with this prior (mm).
        shape: what the geometry step and the report fit: ``"binary"`` (the thresholded shape)
            or ``"occupancy"``.
        max_section_change: a cross-section further than this (relative) from the assumed one is
            not trusted: it is named undetermined and kept (the three cats, with a 56 deg missing
            cone: the gain came out 1.46, a section 31 % below the tank's).
        gain_solver: the solver of step 2 (default ``solver``); the final shape is ``solver``'s.
            The implicit field's smooth shapes bias the cross-section less than voxels do
            (README, "Rig geometry and calibration").

    Returns:
        :class:`SelfCalibration`; its report merges the moment stage's standard errors (heights,
        directions) and the profile stage's (cross-section, with the shape's gauges).
    """
    if shape not in ("occupancy", "binary"):
        raise CalibrationError(f"shape must be 'occupancy' or 'binary', got {shape!r}")
    if not max_section_change > 0:
        raise CalibrationError(f"max_section_change must be positive (relative), got {max_section_change!r}")
    params = _check_params(params)
    model = ProfileModel(raw, grid, n_slabs, operator_factory, smooth, finish)
    state = State(initial or RigGeometry())
    history: list[dict] = []
    rigid = tuple(p for p in params if p != "cross_section_mm2")
    moments = None
    if rigid:  # fit, judge at the estimate, refit without what the data do not determine
        fitted, _ = fit_geometry(model, None, state, rigid, max_nfev=max_nfev)
        moments = identifiability(model, None, fitted, rigid)
        history.append({"stage": "moments, all parameters", **{p: _get(fitted, p, model.nominal_area) for p in params},
                        **{f"se_{p}": moments.standard_errors[p] for p in rigid}})
        active = tuple(p for p in rigid if p not in moments.undetermined)
        if active != rigid and active:
            fitted, _ = fit_geometry(model, None, state, active, max_nfev=max_nfev)
        state = fitted if active else state
        moments = identifiability(model, None, state, rigid)
        history.append({"stage": "moments", **{p: _get(state, p, model.nominal_area) for p in params}})
    volume_params = ("cross_section_mm2",) if "cross_section_mm2" in params else ()
    step_solver = gain_solver or solver
    shape_solver = _with_gain(step_solver) if volume_params else step_solver
    sigma, implausible = None, None
    for it in range(iterations if volume_params or dip_offset_sigma_mm is not None else 0):
        measurement = model.measurement(state)
        recon = shape_solver.solve(measurement, model.operator(measurement.directions))
        occupancy = _shape_volume(recon, shape)
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
        history.append({"stage": f"shape {it}", "gain": gain, **{p: _get(state, p, model.nominal_area) for p in params}})
    for row in history:
        log.info("self-calibration %s", ", ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}"
                                                  for k, v in row.items()))
    if volume_params:  # judged with the last shape (and its dilation gauge); undetermined -> kept at the start
        report = _merge_reports(model, state, moments, volume_params, occupancy, sigma)
        report.caveats["cross_section_mm2"] = (
            "estimated through the shape prior (a nearly binary shape cannot be denser than 1); the standard error "
            "is conditional on the fitted shape and does not hold the prior's bias (bench_calibration, 64^3, "
            f"123 dips: {SECTION_BIAS_NOTE}): for a section better than that, calibrate with a reference object")
        if implausible:
            report.undetermined["cross_section_mm2"] = implausible
        if "cross_section_mm2" in report.undetermined:
            start = (initial or RigGeometry()).cross_section_mm2
            state = replace(state, geometry=state.geometry.with_values(cross_section_mm2=start))
            kept = _get(state, "cross_section_mm2", model.nominal_area)
            report.estimates["cross_section_mm2"] = kept
            report.caveats["cross_section_mm2"] += f"; not determined, kept at {kept:.6g} mm^2"
    measurement = model.measurement(state)
    recon = solver.solve(measurement, model.operator(measurement.directions))
    if not volume_params:
        report = _merge_reports(model, state, moments, volume_params, _shape_volume(recon, shape), sigma)
    _warn_undetermined(report, "self-calibration")
    measurement.metadata = {**measurement.metadata, "self_calibration": report.to_dict(),
                            "geometry": state.geometry.to_dict(), "t0_mm": state.t0_mm}
    recon.info = {**recon.info, "self_calibration": report.to_dict()}
    return SelfCalibration(state.geometry, state.t0_mm, measurement, recon, report, history)


def _with_gain(solver):
    """A copy of ``solver`` that fits a volume gain with the shape (:class:`~dipnet.solvers.optimize.DataTerm`)."""
    if not hasattr(solver, "fit_gain"):
        raise CalibrationError(f"the cross-section is estimated with the shape, which needs an optimisation solver "
                               f"(voxel, implicit); {type(solver).__name__} cannot fit it: drop cross_section_mm2 "
                               "from the parameters or calibrate it with a reference object (scripts/calibrate.py)")
    gained = copy.copy(solver)
    gained.fit_gain = True
    return gained


def _merge_reports(model: ProfileModel, state: State, moments: CalibrationReport | None, volume_params,
                   occupancy: torch.Tensor, sigma: float | None) -> CalibrationReport:
    """The moment stage's report with the profile stage's entries for ``volume_params``."""
    if sigma is None:
        sigma = float(np.sqrt(np.mean(model.residual(state, occupancy, 1.0) ** 2))) or 1.0
    profile = identifiability(model, occupancy, state, volume_params or ("t0_mm",), sigma)
    if moments is None:
        return profile
    if not volume_params:
        return moments
    for name in volume_params:
        moments.estimates[name] = profile.estimates[name]
        moments.standard_errors[name] = profile.standard_errors[name]
        moments.correlations[name] = profile.correlations[name]
        if name in profile.undetermined:
            moments.undetermined[name] = profile.undetermined[name]
    moments.residual_rms, moments.sigma_mm3 = profile.residual_rms, profile.sigma_mm3
    moments.dip_offsets_mm = profile.dip_offsets_mm
    return moments


def _shape_volume(recon: Reconstruction, shape: str) -> torch.Tensor:
    if shape == "binary":
        return torch.from_numpy(recon.binary.astype(np.float64))
    return recon.occupancy.detach().to(torch.float64).clamp(0.0, 1.0)
