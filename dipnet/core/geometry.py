"""The rig's geometry: what a real dipping rig gets wrong, applied (simulator, fake rig) and inverted (readers).

One frozen value object, :class:`RigGeometry`, holds the degrees of freedom of a real rig.
The defaults are the ideal rig the rest of dipnet assumes; every field is a *true* value
relative to what the rig is told:

* ``pivot_mm`` ``p``: the tilt (R1) axis crosses the spin (R2) axis ``p`` mm above the
  object's origin;
* ``tilt_axis_offset_mm`` ``e``: the tilt axis passes ``e`` mm beside the spin axis (in the
  plane of tilting), so tilting also lifts or lowers the object by ``e sin(tilt)``;
* ``tilt_zero_deg``, ``spin_zero_deg``: true angle = commanded angle + zero offset;
* ``step_scale``: true stage travel = ``step_scale`` x commanded travel;
* ``cross_section_mm2``: the tank's true free cross-section ``A`` (``None``: the nominal one
  of the tank / scan header);
* ``level_drift_mm_per_s``: the water level drifts by this rate independently of the object
  (evaporation, temperature), over the whole session;
* ``sensor_lag_s``: the level sensor follows the level with a first-order lag of this time
  constant (s).

Heights. With the spin axis vertical (true tilt 0) the water line at stage 0 lies at
``t0`` in the object frame. Tilting by the true angle ``r`` about the tilt axis moves the
object's origin, and the water line at stage 0 becomes (mm, object frame)

    t_start(r) = t0 + p (cos r - 1) + e sin r          (:meth:`RigGeometry.start_heights`)

which is the issue's ``a + p cos(R1) + e sin(R1)``. The water line at reading ``i`` is
``t_i = t_start + step_scale * s_i + delta_i`` (``s_i`` commanded stage, ``delta_i`` the rise).

Directions: the true rig angles go through :func:`dipnet.core.orientations.rig_to_direction`.

Readings: the water level ``L(t)`` (mm) plus ``level_drift_mm_per_s * t`` (t from the session
start), seen through the sensor lag: a reading taken ``dt`` after the previous one is
``y_i = L_i + (y_{i-1} - L_i) exp(-dt / lag)`` (the level steps when the stage moves and the
sensor settles towards it), the first reading of a dip being settled. :meth:`RigGeometry.apply_levels`
does this, :meth:`RigGeometry.invert_levels` undoes it exactly.

Readers invert a :class:`~dipnet.core.rawscan.RawScan` with :func:`invert_scan` before preprocessing.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np
import torch

from dipnet.core.orientations import rig_to_direction
from dipnet.core.rawscan import OrientationScan, RawScan, ScanHeader

MAX_STEP_SCALE_ERROR = 0.5  # |step_scale - 1| above this is not a rig, it is a typo
MAX_ZERO_OFFSET_DEG = 45.0
MAX_LENGTH_MM = 5000.0
CROSS_SECTION_RANGE_MM2 = (1.0, 1e8)  # 1 mm^2 (or 1 mm in 2D) to a 10 m x 10 m tank
MAX_LEVEL_DRIFT_MM_PER_S = 1.0  # 3.6 m per hour: no tank drifts like that
MAX_SENSOR_LAG_S = 600.0  # longer than any dip step
GEOMETRY_CONFIG_KEY = "rig_geometry"  # ScanHeader.config key: the geometry the rig assumed while scanning


class GeometryError(ValueError):
    """A rig geometry value is unphysical or cannot be applied (the message names the field)."""


@dataclass(frozen=True)
class RigGeometry:
    """The degrees of freedom of a real dipping rig (module docstring); defaults = the ideal rig.

    Attributes:
        pivot_mm: distance of the tilt axis above the object's origin along the spin axis (mm).
        tilt_axis_offset_mm: offset of the tilt axis from the spin axis (mm).
        tilt_zero_deg: zero offset of the tilt axis R1 (true = commanded + offset), degrees.
        spin_zero_deg: zero offset of the spin axis R2, degrees.
        step_scale: true / commanded stage travel (dimensionless).
        cross_section_mm2: the tank's free cross-section (mm^2; mm in 2D); ``None`` = nominal.
        level_drift_mm_per_s: drift of the water level over the session (mm/s).
        sensor_lag_s: first-order time constant of the level sensor (s).
    """

    pivot_mm: float = 0.0
    tilt_axis_offset_mm: float = 0.0
    tilt_zero_deg: float = 0.0
    spin_zero_deg: float = 0.0
    step_scale: float = 1.0
    cross_section_mm2: float | None = None
    level_drift_mm_per_s: float = 0.0
    sensor_lag_s: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name == "cross_section_mm2":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise GeometryError(f"rig geometry {f.name} must be a finite number, got {value!r}")
            object.__setattr__(self, f.name, float(value))
        if self.cross_section_mm2 is not None and not self.cross_section_mm2 > 0:
            raise GeometryError(f"rig geometry cross_section_mm2 must be positive, got {self.cross_section_mm2!r}")
        low, high = CROSS_SECTION_RANGE_MM2
        if self.cross_section_mm2 is not None and not low <= self.cross_section_mm2 <= high:
            raise GeometryError(f"rig geometry cross_section_mm2={self.cross_section_mm2!r} is outside "
                                f"[{low:g}, {high:g}] mm^2: wrong units?")
        if abs(self.level_drift_mm_per_s) > MAX_LEVEL_DRIFT_MM_PER_S:
            raise GeometryError(f"rig geometry level_drift_mm_per_s={self.level_drift_mm_per_s!r} exceeds "
                                f"{MAX_LEVEL_DRIFT_MM_PER_S} mm/s")
        if abs(self.step_scale - 1.0) > MAX_STEP_SCALE_ERROR:
            raise GeometryError(f"rig geometry step_scale={self.step_scale!r} is unphysical "
                                f"(|step_scale - 1| > {MAX_STEP_SCALE_ERROR})")
        for name in ("tilt_zero_deg", "spin_zero_deg"):
            if abs(getattr(self, name)) > MAX_ZERO_OFFSET_DEG:
                raise GeometryError(f"rig geometry {name}={getattr(self, name)!r} exceeds {MAX_ZERO_OFFSET_DEG} deg")
        for name in ("pivot_mm", "tilt_axis_offset_mm"):
            if abs(getattr(self, name)) > MAX_LENGTH_MM:
                raise GeometryError(f"rig geometry {name}={getattr(self, name)!r} exceeds {MAX_LENGTH_MM} mm")
        if not 0 <= self.sensor_lag_s <= MAX_SENSOR_LAG_S:
            raise GeometryError(f"rig geometry sensor_lag_s must be in [0, {MAX_SENSOR_LAG_S:g}] s, "
                                f"got {self.sensor_lag_s!r}")

    # ------------------------------------------------------------------ conversions
    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> "RigGeometry":
        """From a plain mapping; unknown keys raise :class:`GeometryError` naming them. Numbers
        given as strings (YAML 1.1 reads ``1e-4``, without a dot, as one) are converted."""
        values = dict(values or {})
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise GeometryError(f"unknown rig geometry key(s) {unknown}; known: {[f.name for f in fields(cls)]}")
        return cls(**{name: _as_number(value) for name, value in values.items()})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def is_ideal(self) -> bool:
        """Whether this is the ideal rig (the section may still be given explicitly)."""
        return replace(self, cross_section_mm2=None) == RigGeometry()

    def with_values(self, **values: float) -> "RigGeometry":
        """A copy with some fields changed (validated)."""
        return replace(self, **values)

    # ------------------------------------------------------------------ apply / invert
    def area(self, nominal_mm2: float) -> float:
        """The true free cross-section (mm^2): this geometry's, else ``nominal_mm2``."""
        return float(nominal_mm2 if self.cross_section_mm2 is None else self.cross_section_mm2)

    def true_angles(self, tilt_deg, spin_deg) -> tuple[np.ndarray, np.ndarray]:
        """Commanded rig angles ``(K,)`` degrees -> true angles ``(K,)`` degrees."""
        return (np.asarray(tilt_deg, dtype=np.float64) + self.tilt_zero_deg,
                np.asarray(spin_deg, dtype=np.float64) + self.spin_zero_deg)

    def directions(self, tilt_deg, spin_deg) -> torch.Tensor:
        """True unit "up" vectors ``(K, 3)`` for commanded angles ``(K,)`` degrees."""
        return rig_to_direction(*self.true_angles(tilt_deg, spin_deg))

    def height_shift(self, tilt_deg) -> np.ndarray:
        """``p (cos r - 1) + e sin r`` (mm) for commanded tilts ``(K,)`` degrees (true tilt ``r``)."""
        r = np.radians(self.true_angles(tilt_deg, 0.0)[0])
        return self.pivot_mm * (np.cos(r) - 1.0) + self.tilt_axis_offset_mm * np.sin(r)

    def start_heights(self, tilt_deg, t0_mm: float) -> np.ndarray:
        """Water line at stage 0 (mm, object frame) per commanded tilt: ``t0 + height_shift``."""
        return float(t0_mm) + self.height_shift(tilt_deg)

    def true_stage(self, commanded_mm) -> np.ndarray:
        """True stage travel (mm) for commanded positions."""
        return self.step_scale * np.asarray(commanded_mm, dtype=np.float64)

    def _lag_factors(self, time_s: np.ndarray) -> np.ndarray:
        """``exp(-dt / lag)`` per reading ``(n,)``; 0 for the first (settled) reading."""
        c = np.zeros_like(time_s)
        if self.sensor_lag_s > 0 and time_s.size > 1:
            c[1:] = np.exp(-np.maximum(np.diff(time_s), 0.0) / self.sensor_lag_s)
        return c

    def apply_levels(self, levels, time_s) -> np.ndarray:
        """True water levels ``(n,)`` mm of one dip at times ``(n,)`` s -> what the sensor reads."""
        time_s = np.asarray(time_s, dtype=np.float64)
        level = np.asarray(levels, dtype=np.float64) + self.level_drift_mm_per_s * time_s
        c = self._lag_factors(time_s)
        out = level.copy()
        for i in range(1, len(out)):
            out[i] = level[i] + (out[i - 1] - level[i]) * c[i]
        return out

    def invert_levels(self, readings, time_s) -> np.ndarray:
        """Inverse of :meth:`apply_levels`: sensor readings ``(n,)`` -> drift-free water levels ``(n,)``."""
        time_s = np.asarray(time_s, dtype=np.float64)
        y = np.asarray(readings, dtype=np.float64)
        c = self._lag_factors(time_s)
        level = y.copy()
        level[1:] = (y[1:] - c[1:] * y[:-1]) / (1.0 - c[1:])
        return level - self.level_drift_mm_per_s * time_s


def as_geometry(value) -> RigGeometry:
    """A :class:`RigGeometry` from itself, a mapping of its fields (e.g. a Hydra config) or ``None`` (ideal)."""
    if isinstance(value, RigGeometry):
        return value
    return RigGeometry.from_dict(None if value is None else {str(k): v for k, v in dict(value).items()})


def scan_geometry(header: ScanHeader) -> RigGeometry:
    """The geometry a raw scan's rig assumed while recording (its per-dip ``t_start_mm`` already
    hold that geometry's height shift); the ideal rig when the header records none."""
    return RigGeometry.from_dict(header.config.get(GEOMETRY_CONFIG_KEY))


def invert_scan(raw: RawScan, geometry: RigGeometry) -> RawScan:
    """Map a raw scan's readings through ``geometry``: a copy whose readings are what an ideal rig
    would have recorded, ready for :func:`dipnet.preprocessing.preprocess.preprocess`.

    Per orientation: true directions from the commanded rig angles (orientations without
    angles keep their direction; non-zero zero offsets then raise), true stage travel, levels
    without drift and lag (level scans; a balance reading is not a level and is left as is),
    the start height ``t_start_mm`` (meta or header) moved by ``geometry``'s height shift minus
    the one the rig already applied (:func:`scan_geometry`), and the header's cross-section
    replaced by the geometry's.

    Raises:
        GeometryError: angle offsets for a scan without rig angles, drift or lag for a scan
            without reading times (the authors' CSV).
    """
    header = raw.header
    applied = scan_geometry(header)
    timed = header.metadata.get("format") != "authors_csv"
    if not timed and (geometry.level_drift_mm_per_s or geometry.sensor_lag_s):
        raise GeometryError("level drift and sensor lag need reading times, which this recording "
                            f"({header.metadata.get('source', raw.path)}) does not have")
    area = geometry.area(header.tank_cross_section_mm2) if header.tank_cross_section_mm2 or \
        geometry.cross_section_mm2 else None
    out = RawScan(header=replace(header, tank_cross_section_mm2=area,
                                 config={**header.config, "inverted_geometry": geometry.to_dict()}),
                  truncated=raw.truncated, path=raw.path)
    for o in raw.orientations:
        angles = o.tilt_deg is not None and o.spin_deg is not None
        if not angles and (geometry.tilt_zero_deg or geometry.spin_zero_deg or geometry.pivot_mm
                           or geometry.tilt_axis_offset_mm):
            raise GeometryError(f"orientation {o.k} has no rig angles: the rotary-axis geometry cannot apply")
        meta = dict(o.meta)
        direction = o.direction
        if angles:
            direction = geometry.directions(o.tilt_deg, o.spin_deg)[0].numpy()
            recorded = meta.get("t_start_mm", header.t_start_mm)
            if recorded is not None:
                shift = geometry.height_shift(o.tilt_deg) - applied.height_shift(o.tilt_deg)
                meta["t_start_mm"] = float(recorded + shift)
        values = geometry.invert_levels(o.values, o.time_s) if header.quantity == "level_mm" else o.values
        out.orientations.append(OrientationScan(
            k=o.k, direction=direction, tilt_deg=o.tilt_deg, spin_deg=o.spin_deg, meta=meta,
            stage_mm=geometry.true_stage(o.stage_mm), values=values, time_s=o.time_s.copy(),
            flags=[list(f) for f in o.flags], complete=o.complete))
    return out


def _as_number(value: Any) -> Any:
    """``value`` as a float when it is a string holding a number, else unchanged (the dataclass
    check then names what is wrong with it)."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value
