"""Measurement validation before any solver: refuse what cannot be right, warn about what disagrees.

:func:`validate_measurement` checks a :class:`~dipnet.core.measurement.DipMeasurement` against the
reconstruction grid and returns a :class:`ValidationReport` (its :meth:`~ValidationReport.metrics`
go into ``metrics.json``). The rules (``V_k`` = the total of profile ``k``, ``V_ball`` = the
volume of the grid's working ball, ``s_k`` = the noise of ``V_k``: ``sqrt(sum_j sigma_kj^2)``
when the measurement carries ``sigma``, else 0):

* **finite**: NaN or infinite values: error.
* **magnitude**: an object inside the working ball displaces at most ``V_ball``; any
  ``|V_k|`` or slab above ``V_ball (1 + size_tol)``: error (wrong units, a scaled file, a grid
  too small for the object). A largest ``V_k`` below one voxel's volume: error too (an object the grid
  cannot hold a voxel of: litres or m^2 where mm^3 or mm^2 are meant, or an extent far too large).
* **reach**: an object beyond the working ball (radius ``extent/2 - voxel``, the frame's origin its centre) has
  parts no voxel holds: the operators ignore every voxel outside it, so the volume there is put inside or
  lost. Each dip shows heights below and above which some of the object lies
  (:meth:`~dipnet.core.measurement.DipMeasurement.reach`: from the readings when preprocessing recorded them,
  else from the first and last non-empty slab, beyond :data:`~dipnet.core.measurement.REACH_SIGMAS` noise
  sigmas); one beyond the ball's radius: error, naming the ``extent_mm`` that would hold it, as a simulated
  shape larger than the ball is refused (:class:`dipnet.simulator.source.SimulatedSource`). Truncated dips kept
  with a flat tail are left out: where the recording has no start heights (the authors' CSV) theirs are the
  rig geometry's extrapolation from the complete dips (the authors' 35 deg dips lie ~16 mm off). The slabs' share
  beyond the grid (``outside_share``) does not show it: slabs reach half a voxel or more past the ball.
  A wrong rig geometry (another rig's calibration file) shifts every dip's heights and reads as an object far off
  the centre, so the refusal first asks whether the dips place one object at all (:func:`dip_placement`: the
  dips of a rigid object fit, about one of its points, within its widest dip); when they do not, it names the
  geometry (the calibration file the reader was given, or the values) instead of the grid. A geometry from a
  calibration file is named in either case. The check runs before the signs: a dip misplaced wholly off the
  slabs sums to 0.
* **sign**: slab volumes are non-negative. A profile whose total is not positive: error.
  Negative slabs below ``-max(4 sigma_kj, neg_tol max_j |p_kj|)`` are beyond noise: error when
  their magnitude exceeds ``neg_tol`` of the positive volume, else a warning.
* **totals**: every dip measures the same object, so the totals agree within noise. The spread
  (``(max - min) / median``) is reported; totals off the median by more than
  ``max(5 s_k, total_tol median)`` give a warning naming them (truncated dips do this too, and air trapped
  in a cavity that opens downward along some dips: :mod:`dipnet.simulator.pockets`).
* **duplicates**: directions within ``dup_deg`` of each other are reported. Such pairs measure
  the same profile at the same heights: when their cumulative profiles (the volume below each
  height, on the slabs' own heights) differ anywhere by more than ``max(5 noise, total_tol V)``, a
  warning gives the discrepancy (a direction mislabelled, or repeated by mistake, measures another
  profile with the same total). The profiles are kept (a least-squares solver averages them).
* **hemisphere**: a direction is the object's "up" in the tank, and every rig's and every orientation set's
  lie on the upper half (last component >= 0: tilts up to 90 deg). Two or more directions, none above the
  horizontal and some below: a warning. A file that records the direction of motion (down) instead dips the
  object along the reversed directions, whose profiles are the point-reflected object's: a shape that explains
  the dips exactly, mirrored through the centre, which no data check can tell from the right one.

Errors raise :class:`MeasurementValidationError` (one line, the first problem found);
warnings go to the log and to :mod:`warnings`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import cKDTree

from dipnet.core.framing import extent_around
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid, as_grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.warn import log_and_warn

log = logging.getLogger(__name__)

_MAD = 1.4826  # MAD -> standard deviation for Gaussian data

#: Gain of the third difference ``[-1, 3, -3, 1]`` on white noise: ``sqrt(1 + 9 + 9 + 1)``.
_THIRD_DIFFERENCE_GAIN = math.sqrt(20.0)
#: The readings' noise estimate holds their noise alone when it grows by less than this with the step doubled
#: (:func:`reading_noise_leak`)
NOISE_LEAK_MAX = 2.0


def reading_noise(readings: list[np.ndarray], stated: list[float | None], quantum: float = 0.0
                  ) -> tuple[float, float]:
    """The readings' own noise and the stated noise over it: ``(sigma, stated / sigma)``.

    A dip's readings (level or balance, one per stage step) are a smooth rise plus white noise, so
    their third differences along the stage hold the noise alone (the rise's own third difference
    over a 1 mm step is far below it); the robust sigma (MAD) of all dips' third differences over
    their white-noise gain estimates the noise per reading. The slab profiles cannot give it: they
    interpolate the readings (slabs thinner than a step hold almost none of their noise) and the
    monotone fit flattens it where the level barely rises, while at a few mm per slab the
    profiles' own shape outweighs a 30 dB noise. Rounding to ``quantum`` leaves ``quantum / sqrt(12)``
    at least, which bounds the estimate from below (readings that stay on one level for several steps
    show no scatter).

    Args:
        readings: each dip's readings ``(n_k,)`` in their unit (mm or g), by stage position.
        stated: each dip's stated noise sigma (same unit; 0 for a noise-free sensor, whose
            rounding alone is then stated), ``None`` when not stated.
        quantum: the readings' resolution (same unit; 0: none).

    Returns:
        ``sigma`` (reading unit; NaN without a dip of 4 readings) and the median stated sigma
        (with the rounding's, as preprocessing states the slab noise) over ``sigma``; NaN when no
        dip states its noise.
    """
    third = [np.diff(np.asarray(v, dtype=np.float64), 3) for v in readings if len(v) >= 4]
    if not third:
        return float("nan"), float("nan")
    rounding = quantum / math.sqrt(12.0)
    sigma = max(_third_difference_sigma(third), rounding)
    given = [math.hypot(s, rounding) for s in stated if s is not None]
    if not given or not sigma > 0 or not float(np.median(given)) > 0:
        return sigma, float("nan")
    return sigma, float(np.median(given)) / sigma


def _third_difference_sigma(differences: list[np.ndarray]) -> float:
    """The robust sigma (MAD) of the concatenated third differences over their white-noise gain; NaN for none."""
    if not differences:
        return float("nan")
    d = np.concatenate(differences)
    return _MAD * float(np.median(np.abs(d - np.median(d)))) / _THIRD_DIFFERENCE_GAIN


def reading_noise_leak(readings: list[np.ndarray]) -> float:
    """How much of the rise itself :func:`reading_noise` took for noise: the same estimate from every other
    reading (both phases; the step doubled) over the estimate from every reading.

    White noise gives the same sigma at either step (ratio 1); the rise's own third difference grows with the
    step's cube, so a ratio well above 1 says the estimate holds the rise too, and the readings' noise is smaller
    than it says. On five bundled meshes and the built-in box (41 dips, 0.5-5 mm steps, 10-60 dB), where the ratio was
    below 2 the true noise was 0.70-1.0 of the estimate, and where the estimate exceeded twice the true noise the ratio
    was 2.5 or more. NaN without a dip of 8 readings.
    """
    full = [np.diff(np.asarray(v, dtype=np.float64), 3) for v in readings if len(v) >= 8]
    halves = [np.diff(np.asarray(v, dtype=np.float64)[start::2], 3)
              for v in readings if len(v) >= 8 for start in (0, 1)]
    sigma = _third_difference_sigma(full)
    return _third_difference_sigma(halves) / sigma if sigma > 0 else float("nan")


class MeasurementValidationError(ValueError):
    """The measurement cannot describe an object in the grid (negative, huge, non-finite...)."""


@dataclass
class ValidationReport:
    """What :func:`validate_measurement` found.

    Attributes:
        warnings: one-line findings that did not stop the run.
        stats: numbers behind them (totals, spread, duplicates, ...), JSON-serialisable.
    """

    warnings: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    def metrics(self) -> dict:
        """Entries for ``metrics.json``: flat counts plus the details under ``validation``."""
        readings = self.stats.get("readings", {})
        return {"readings_repaired": int(readings.get("readings_repaired", 0)),
                "dips_rejected": int(readings.get("dips_rejected", 0)),
                "readings_flagged": int(readings.get("readings_flagged", 0)),
                "dips_truncated_dropped": int(self.stats.get("truncated_dropped", 0)),
                "dips_incomplete_dropped": len(self.stats.get("incomplete_dropped", [])),
                "validation_warnings": len(self.warnings),
                "validation": {**self.stats, "warnings": self.warnings}}


def working_ball_volume(grid: Grid) -> float:
    """Volume (mm^3; area in mm^2 in 2D) of the grid's working ball."""
    r = grid.radius
    return 4.0 / 3.0 * math.pi * r**3 if grid.ndim == 3 else math.pi * r**2


def validate_measurement(measurement: DipMeasurement, grid: Grid, *, size_tol: float = 0.05,
                         neg_tol: float = 0.02, total_tol: float = 0.05, dup_deg: float = 0.5) -> ValidationReport:
    """Check ``measurement`` against ``grid`` by the module's rules.

    Args:
        measurement: profiles ``(K, M)`` (mm^3; mm^2 in 2D), directions ``(K, d)``.
        grid: the reconstruction grid (its working ball bounds the object).
        size_tol, neg_tol, total_tol: relative tolerances, see the module docstring.
        dup_deg: directions closer than this (degrees) are duplicates.

    Raises:
        MeasurementValidationError: the first error found.
    """
    source = measurement.metadata.get("path") or measurement.metadata.get("rawscan") or "measurement"
    prof = measurement.profiles.numpy()
    grid = as_grid(grid)
    if measurement.ndim != grid.ndim:
        raise MeasurementValidationError(f"{source}: {measurement.ndim}D directions for a {grid.ndim}D grid: "
                                         f"set ndim={measurement.ndim}")
    if not np.isfinite(prof).all() or not np.isfinite(measurement.directions.numpy()).all():
        raise MeasurementValidationError(f"{source}: the profiles or directions hold NaN or infinite values")
    sigma = None if measurement.sigma is None else measurement.sigma.numpy()
    recorded = measurement.metadata.get("recorded") or {}
    dropped = len(recorded.get("truncated", [])) if recorded.get("truncated_policy") == "drop" else 0
    report = ValidationReport(stats={"readings": measurement.metadata.get("readings", {}), "truncated_dropped": dropped,
                                     "incomplete_dropped": list(recorded.get("incomplete", []))})
    _check_configured_section(recorded.get("cross_section_mm2"), source, report)
    _check_magnitude(prof, grid, size_tol, source)
    totals = prof.sum(axis=1)
    noise = np.zeros(len(prof)) if sigma is None else np.sqrt((sigma**2).sum(axis=1))
    _check_reach(measurement, grid, source)  # before the signs: a dip misplaced off the slabs sums to 0
    unit = grid.volume_unit
    _check_signs(prof, totals, sigma, neg_tol, source, report, unit)
    _check_not_tiny(totals, grid, source)
    _check_totals(totals, noise, total_tol, source, report, unit)
    _check_duplicates(measurement, totals, noise, total_tol, dup_deg, source, report, unit)
    _check_hemisphere(measurement.directions.double().numpy(), source, report)
    for message in report.warnings:
        log_and_warn(log, message, stacklevel=2)
    return report


#: A configured tank section this far (relative) from the one the recording states is warned about.
SECTION_TOL = 0.01


def _check_configured_section(section: dict | None, source: str, report: ValidationReport) -> None:
    """Record the tank section a recording was read with (``section``: ``used``, ``recorded`` and ``configured``,
    mm^2, from :func:`~dipnet.preprocessing.recorded.prepare_recording`) and warn when a configured one replaces
    a different one the recording states: every slab volume scales with it, and the dips cannot tell (a scan of
    the built-in box stated at 20,000 mm^2 and read at 26,000: IoU 0.76 against 0.95, ``consistent``)."""
    if not section:
        return
    report.stats["cross_section_mm2"] = section
    recorded, configured = section.get("recorded"), section.get("configured")
    if recorded and configured and abs(configured / recorded - 1.0) > SECTION_TOL:
        report.warnings.append(
            f"{source}: the configured tank section {configured:g} mm^2 replaces the {recorded:g} mm^2 the recording "
            f"states ({configured / recorded - 1.0:+.0%}): every slab volume, and so the object's size, scales with "
            "it; unset source.reader.cross_section_mm2 (or the geometry's) to read the recording's")


def _check_magnitude(prof: np.ndarray, grid: Grid, size_tol: float, source: str) -> None:
    ball = working_ball_volume(grid)
    largest = float(max(np.abs(prof).max(), np.abs(prof).sum(axis=1).max()))
    if largest > ball * (1 + size_tol):
        raise MeasurementValidationError(
            f"{source}: a profile holds {largest:.4g} {grid.volume_unit}, more than the working ball's {ball:.4g} "
            f"{grid.volume_unit} "
            f"(extent_mm={grid.extent:g}): wrong units or scale, or increase extent_mm")


def _check_not_tiny(totals: np.ndarray, grid: Grid, source: str) -> None:
    total = float(totals.max())
    if total < grid.voxel_volume:
        raise MeasurementValidationError(
            f"{source}: the largest profile holds {total:.4g} {grid.volume_unit}, less than one voxel's "
            f"{grid.voxel_volume:.4g} {grid.volume_unit} (extent_mm={grid.extent:g}, resolution {grid.n}): "
            "wrong units or "
            f"scale ({_UNIT_SLIPS[grid.ndim]}), or an extent far too large for the object")


#: Unit slips that make a measurement too small to hold a voxel, by ``ndim``: named in the refusal.
_UNIT_SLIPS = {3: "litres for mm^3, a cross-section in m^2", 2: "cm^2 or m^2 for mm^2, a slot width in m"}

#: The share of the working ball an object fills when the grid is chosen around it (``fill``, conf/config.yaml).
_DEFAULT_FILL = 0.9


def _check_reach(measurement: DipMeasurement, grid: Grid, source: str) -> None:
    """Refuse a measurement whose object reaches beyond ``grid``'s working ball (see the module docstring)."""
    far, dip = object_reach(measurement)
    if far >= grid.radius * (1 - 1e-9):  # NaN compares False
        message = beyond_ball_message(far, grid, dip, placement=dip_placement(measurement),
                                      geometry=geometry_origin(measurement))
        raise MeasurementValidationError(f"{source}: {message}")


def _reach_rows(measurement: DipMeasurement) -> np.ndarray:
    """Each measured dip's :meth:`~dipnet.core.measurement.DipMeasurement.reach` ``(K', 2)`` (mm), with the
    truncated dips kept with a flat tail set to NaN (see the module docstring)."""
    reach = measurement.reach().copy()  # (K', 2) heights [low, high], mm
    ks = measurement.metadata.get("orientation_k") or []
    recorded = measurement.metadata.get("recorded") or {}
    if recorded.get("truncated_policy") == "keep" and len(ks) == len(reach):
        reach[np.isin(ks, recorded.get("truncated", []))] = np.nan  # placed by the complete dips' geometry
    return reach


def object_reach(measurement: DipMeasurement) -> tuple[float, str]:
    """``(reach, dip)``: how far (mm) from the frame's origin, the grid's centre, the dips show the object
    reaching (the largest over the dips of :meth:`~dipnet.core.measurement.DipMeasurement.reach`; NaN when no dip
    shows volume) and the dip that shows it (``"orientation k"``). Truncated dips kept with a flat tail are left
    out (see the module docstring)."""
    reach = _reach_rows(measurement)
    far = np.fmax(-reach[:, 0], reach[:, 1])  # NaN only for a dip with no volume
    ks = measurement.metadata.get("orientation_k") or []
    if not np.isfinite(far).any():
        return float("nan"), ""
    worst = int(np.nanargmax(far))
    return float(far[worst]), f"orientation {ks[worst]}" if len(ks) == len(far) else f"dip {worst}"


#: The dips of one rigid object fit within its widest dip about any of its points (below); the reaches found fall
#: short of the object's by their noise, so a placement is implausible only beyond this factor of the widest dip.
#: Dips placed by their own rig geometry need 0.50 of it (four bundled meshes at 10-40 dB, a ball, the authors'
#: cats); another rig's geometry (pivot and offset 40-90 mm off) 1.3-3.1, a pivot 40 mm off alone 0.65-1.2.
PLACEMENT_FACTOR = 1.2


@dataclass(frozen=True)
class Placement:
    """Whether the dips' heights place one rigid object (:func:`dip_placement`).

    Attributes:
        radius_mm: the smallest radius of a ball, about one centre, along whose every dip direction the dip's
            reach ``[low, high]`` lies within the ball's (mm).
        width_mm: the widest dip's ``high - low`` (mm): the object is at least this wide.
        centre_mm: that ball's centre (mm, object frame).
    """

    radius_mm: float
    width_mm: float
    centre_mm: tuple[float, ...]

    @property
    def implausible(self) -> bool:
        """More than :data:`PLACEMENT_FACTOR` widest dips: no one object is placed so."""
        return self.radius_mm > PLACEMENT_FACTOR * self.width_mm


def dip_placement(measurement: DipMeasurement) -> Placement | None:
    """How well one rigid object explains where the dips show volume.

    Dip ``k`` shows some of the object below ``low_k`` and above ``high_k`` along its direction ``theta_k``
    (:meth:`~dipnet.core.measurement.DipMeasurement.reach`). For an object ``O`` and any of its points ``p``,
    ``high_k - p . theta_k`` and ``p . theta_k - low_k`` are at most the dip's width ``high_k - low_k``, so the
    smallest radius ``R`` with ``[low_k, high_k]`` inside ``c . theta_k +- R`` for one centre ``c`` (a linear
    programme) is at most the widest dip ``W`` (about ``W / 2`` for compact objects). Heights shifted by a wrong
    rig geometry (``a (cos r - 1) + b sin r``, which no ``c . theta`` takes up) make ``R`` exceed ``W``.

    Returns:
        The :class:`Placement`, or ``None`` with fewer than ``ndim + 2`` dips that show volume, or when symmetry
        images were merged into the dips (their reach rows no longer pair with the directions).
    """
    reach = _reach_rows(measurement)
    if len(reach) != measurement.n_orientations and "symmetry_group_order" in measurement.metadata:
        return None
    directions = measurement.directions.double().numpy()[:len(reach)]  # interpolated directions follow the dips
    use = np.isfinite(reach).all(axis=1)
    reach, directions = reach[use], directions[use]
    k, d = directions.shape
    if k < d + 2:
        return None
    ones = np.ones((k, 1))
    bounds = np.vstack([np.hstack([-directions, -ones]), np.hstack([directions, -ones])])  # over (c, R)
    fit = linprog(np.r_[np.zeros(d), 1.0], A_ub=bounds, b_ub=np.concatenate([-reach[:, 1], reach[:, 0]]),
                  bounds=[(None, None)] * d + [(0.0, None)], method="highs")
    if not fit.success:
        return None
    return Placement(float(fit.x[-1]), float((reach[:, 1] - reach[:, 0]).max()), tuple(float(v) for v in fit.x[:d]))


def geometry_origin(measurement: DipMeasurement) -> dict:
    """Where the rig geometry that placed the dips came from, from what the reader recorded
    (``metadata["recorded"]``): ``{"calibration": {path, rig, tank, method, created}}`` for a calibration file,
    ``{"values": {field: value}}`` for geometry values off the ideal rig, ``{"ideal": True}`` for the ideal rig;
    empty when the measurement does not say (a simulation, a saved ``.npz``)."""
    recorded = measurement.metadata.get("recorded") or {}
    if recorded.get("calibration"):
        return {"calibration": recorded["calibration"]}
    geometry = recorded.get("geometry")
    if not isinstance(geometry, dict):
        return {}
    ideal = RigGeometry().to_dict()
    values = {name: value for name, value in geometry.items()
              if name != "cross_section_mm2" and value is not None and value != ideal.get(name)}
    return {"values": values} if values else {"ideal": True}


def beyond_ball_message(reach: float, grid: Grid, dip: str = "", *, placement: Placement | None = None,
                        geometry: dict | None = None) -> str:
    """The finding for an object that reaches ``reach`` mm from the centre of ``grid``, beyond its working ball
    (shown by ``dip``), naming the ``extent_mm`` that puts ``reach`` at :data:`_DEFAULT_FILL` of the ball.

    With the dips' ``placement`` (:func:`dip_placement`) implausible for one object, the rig geometry is named
    as the cause instead (what to do depends on ``geometry``, :func:`geometry_origin`); a geometry from a
    calibration file is named in either case."""
    needed = math.ceil(extent_around(reach, grid.n, _DEFAULT_FILL))
    found = (f"the object reaches beyond the working ball of radius {grid.radius:.1f} mm (extent_mm={grid.extent:g} "
             f"at resolution {grid.n}): the dips hold volume at least {reach:.1f} mm from the grid's centre"
             f"{f' ({dip})' if dip else ''}")
    if placement is not None and placement.implausible:
        return f"{found}, {_misplaced(placement, geometry or {}, needed)}"
    message = (f"{found}, where no voxel can hold it: increase extent_mm to {needed} or more (which puts "
               f"{reach:.1f} mm at {_DEFAULT_FILL:.0%} of the ball's radius, as a grid chosen around a shape does)")
    file = (geometry or {}).get("calibration")
    if file:
        width = f" (no dip shows it wider than {placement.width_mm:.1f} mm)" if placement is not None else ""
        message += (f". The rig geometry comes from the calibration file {_calibration_name(file)}: if the object is "
                    f"not that far off the spin axis{width}, check that the file is this rig's, "
                    "or recalibrate this rig")
    return message


def _misplaced(placement: Placement, geometry: dict, needed: int) -> str:
    """Why dips that place no one object are not the grid's fault, and what to do about the geometry."""
    finding = (f"yet no dip shows it wider than {placement.width_mm:.1f} mm and their heights place no one object "
               f"(about any centre they need a radius of {placement.radius_mm:.1f} mm, where one object's dips fit "
               f"within its widest): the rig geometry misplaces the dips' heights, not the grid")
    recalibrate = ("recalibrate this rig (scripts/calibrate.py on a reference ball, or calibration=self), then read "
                   "the scan with the new file")
    if geometry.get("calibration"):
        cause = (f"; it comes from the calibration file {_calibration_name(geometry['calibration'])}: check that the "
                 f"file is this rig's current calibration (not another rig's of the same name, nor an old one), or "
                 f"{recalibrate}")
    elif geometry.get("values"):
        values = ", ".join(f"{name}={value:.6g}" for name, value in geometry["values"].items())
        cause = f"; the geometry given ({values}) is likely wrong: check the values, or {recalibrate}"
    elif geometry.get("ideal"):
        cause = ("; the scan is read on the ideal rig (no geometry given): give the reader this rig's calibration "
                 "file (source.reader.calibration=FILE) or geometry, or calibrate it (calibrate.py, calibration=self)")
    else:
        cause = "; check the rig geometry and the dips' start heights"
    return f"{finding}{cause}. A larger extent_mm ({needed}) would only hold a misplaced object"


def _calibration_name(file: dict) -> str:
    """A calibration file as ``path (rig 'r', tank 't', method, created ...)`` from :func:`geometry_origin`."""
    details = [f"rig {file['rig']!r}" if file.get("rig") else "", f"tank {file['tank']!r}" if file.get("tank") else "",
               str(file.get("method") or ""), f"created {file['created']}" if file.get("created") else ""]
    listed = ", ".join(d for d in details if d)
    return f"{file.get('path', '?')}{f' ({listed})' if listed else ''}"


def _check_signs(prof, totals, sigma, neg_tol: float, source: str, report: ValidationReport, unit: str) -> None:
    worst = int(np.argmin(totals))
    if totals[worst] <= 0:
        raise MeasurementValidationError(f"{source}: profile {worst} sums to {totals[worst]:.4g} {unit}: "
                                         "a dip cannot displace a negative or zero volume")
    floor = neg_tol * np.abs(prof).max(axis=1, keepdims=True)
    if sigma is not None:
        floor = np.maximum(floor, 4.0 * sigma)
    beyond = prof < -floor
    negative = float(np.abs(prof[prof < 0]).sum())
    positive = float(prof[prof > 0].sum())
    report.stats.update(negative_slabs=int((prof < 0).sum()), negative_beyond_noise=int(beyond.sum()),
                        negative_fraction=negative / positive)
    if beyond.any():
        message = (f"{source}: {int(beyond.sum())} slab volume(s) are negative beyond noise (down to "
                   f"{prof.min():.4g} {unit}; {negative / positive:.1%} of the positive volume)")
        if negative > neg_tol * positive:
            raise MeasurementValidationError(message)
        report.warnings.append(message)


def _check_totals(totals, noise, total_tol: float, source: str, report: ValidationReport, unit: str) -> None:
    median = float(np.median(totals))
    allowed = np.maximum(5.0 * noise, total_tol * median)
    off = np.flatnonzero(np.abs(totals - median) > allowed)
    report.stats.update(total_median_mm3=median, total_min_mm3=float(totals.min()),
                        total_max_mm3=float(totals.max()), total_spread=float(np.ptp(totals) / median),
                        total_noise_rel=float(np.median(noise) / median), totals_off=[int(k) for k in off])
    if off.size:
        report.warnings.append(
            f"{source}: {off.size} of {len(totals)} dip total(s) differ from the median {median:.4g} {unit} by more "
            f"than noise explains (range {totals.min():.4g}..{totals.max():.4g}; dips {off[:8].tolist()}"
            f"{'...' if off.size > 8 else ''}): truncated dips, leaks or bad readings? Totals above the rest also come "
            "from air trapped in a cavity that opens downward along those dips (it displaces water as the object does)")


def _cumulative_gap(measurement: DipMeasurement, i: int, j: int) -> float:
    """The largest difference (mm^3) between the volumes below a height of dips ``i`` and ``j``, each
    cumulative profile taken on its own slab heights (``offsets + h * m``) and linear in between."""
    h = measurement.slab_thickness
    edges = [float(measurement.offsets[k]) + h * np.arange(measurement.n_slabs + 1) for k in (i, j)]
    heights = np.union1d(*edges)
    below = [np.interp(heights, e, np.concatenate([[0.0], np.cumsum(measurement.profiles[k].double().numpy())]))
             for e, k in zip(edges, (i, j))]
    return float(np.abs(below[0] - below[1]).max())


def _check_duplicates(measurement: DipMeasurement, totals, noise, total_tol: float, dup_deg: float, source: str,
                      report: ValidationReport, unit: str) -> None:
    directions = measurement.directions.double().numpy()
    lines = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    chord = 2.0 * math.sin(math.radians(dup_deg) / 2.0)
    pairs = np.array(sorted(cKDTree(lines).query_pairs(chord)), dtype=int).reshape(-1, 2)
    report.stats["duplicate_direction_pairs"] = int(len(pairs))
    if not len(pairs):
        return
    i, j = pairs[:, 0], pairs[:, 1]
    scale = 0.5 * (totals[i] + totals[j])
    gap = np.array([_cumulative_gap(measurement, a, b) for a, b in pairs])
    allowed = np.maximum(5.0 * np.hypot(noise[i], noise[j]), total_tol * scale)
    disagree = gap > allowed
    worst = int(np.argmax(gap / scale))
    report.stats["duplicate_max_discrepancy"] = float(gap[worst] / scale[worst])
    if disagree.any():
        report.warnings.append(
            f"{source}: {int(disagree.sum())} of {len(pairs)} pair(s) of directions within {dup_deg:g} deg measure "
            f"different profiles (worst: dips {i[worst]} and {j[worst]}, whose volumes below a height differ by "
            f"up to {gap[worst]:.4g} {unit}, {gap[worst] / scale[worst]:.1%} of {scale[worst]:.4g} {unit}): "
            "a direction "
            "mislabelled, or the same direction recorded for different dips?")


def _check_hemisphere(directions: np.ndarray, source: str, report: ValidationReport) -> None:
    """Warn when two or more ``directions`` ``(K, d)`` point below the horizontal and none above it (the module's
    **hemisphere** rule)."""
    down = directions[:, -1] < 0.0
    report.stats["directions_down"] = int(down.sum())
    if len(directions) >= 2 and down.any() and (directions[:, -1] <= 0.0).all():  # horizontal ones go either way
        axis = "z" if directions.shape[1] == 3 else "y"
        report.warnings.append(
            f"{source}: every direction points down ({axis} < 0 in {int(down.sum())} of {len(directions)}, none "
            f"above 0), where a direction is the "
            "object's up in the tank and every rig's lie on the upper half: if the file records the direction of "
            "motion, negate them, or the shape comes out point-reflected through the centre (it explains the dips "
            "as well, so no later check can tell)")

