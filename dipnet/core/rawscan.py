"""RawScan: what a dipping rig (or the simulator) records, and its append-only file format.

A raw scan holds, per orientation, every reading taken while the object was lowered step by
step: the commanded stage position (mm, *increasing = lowered further*), the sensor value
(water level in mm, or balance reading in g, see :attr:`ScanHeader.quantity`), the time (s)
and flags (e.g. ``"unstable"``). :mod:`dipnet.preprocessing.preprocess` turns it into a
:class:`~dipnet.core.measurement.DipMeasurement`.

File format (version 1, JSON Lines, UTF-8, one JSON object per line)
--------------------------------------------------------------------
::

    {"type": "header", "format": "dipnet.rawscan", "version": 1, "quantity": "level_mm", ...}
    {"type": "orientation", "k": 0, "direction": [x, y, z], "tilt_deg": 10.0, "spin_deg": 0.0, "meta": {}}
    {"type": "reading", "k": 0, "stage_mm": 0.0, "value": 150.0, "time_s": 0.0, "flags": []}
    ...
    {"type": "complete", "k": 0, "n_readings": 87}
    {"type": "orientation", "k": 1, ...}

A rig run also writes, once per connection and before its first orientation, what it found
after connecting (a resumed scan has one per run)::

    {"type": "session", "first_k": 1, "time": "2026-11-23T16:10:00+0000",
     "controller": {"dialect": "grbl", "firmware": "1.1h", "build": ["[VER:1.1h.20190830:]", ...], ...},
     "sensor": {"kind": "LineSensor", ...}}

The writer flushes (and by default fsyncs) after every line, so a crash loses at most the
line being written. The reader tolerates a truncated last line, and an orientation whose
``complete`` line is missing is reported as incomplete: a scan resumes after its last complete
orientation (:meth:`RawScan.complete_orientations`, :meth:`RawScan.next_orientation`). A new
``orientation`` line for an index that was started but not completed restarts that
orientation (its earlier readings are dropped); consumers leave incomplete orientations out
with a warning naming them (:func:`complete_dips`). Within an orientation the stage never moves
back (the rig only lowers; equal positions are repeats): a reading at a lower stage than the one
before is an error, not sorted silently; reading times that run backwards within a dip are kept with a
warning naming the line (a wall clock set back leaves sound readings, but not times to fit a drift by).
The header's ``quantity`` must agree with its ``units`` and with ``config.sensor.quantity`` when those
are recorded. The header's ``units`` (dipnet writes mm, mm^2, g, s, deg) may declare other units for a field
(:data:`UNITS`, e.g. ``"units": {"stage": "in"}``): the reader converts the readings, the step, the noise and resolution
and the cross-section to dipnet's units, and refuses a unit it does not know, naming the field
(``t_start_mm`` and the orientations' ``meta`` stay in mm). Any other malformed
line raises :class:`RawScanFileError` naming the file and the line number.
"""

from __future__ import annotations

import json
import logging
import numbers
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.orientations import rig_to_direction
from dipnet.core.strict_json import DuplicateKeyError, unique_keys
from dipnet.core.warn import log_and_warn

log = logging.getLogger(__name__)

FORMAT_NAME = "dipnet.rawscan"
FORMAT_VERSION = 1
QUANTITIES = {"level_mm": "mm", "mass_g": "g"}
#: Units a header's ``units`` may declare, per kind, as factors to dipnet's unit (first of each).
LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
UNITS: dict[str, dict[str, float]] = {
    "length": LENGTH_UNITS,
    "mass": {"g": 1.0, "kg": 1000.0},
    "time": {"s": 1.0, "ms": 1e-3, "min": 60.0},
    "angle": {"deg": 1.0, "rad": 180.0 / np.pi},
    "area": {f"{unit}^2": factor ** 2 for unit, factor in LENGTH_UNITS.items()},
}
WATER_DENSITY_G_PER_MM3 = 1e-3


class RawScanFileError(ValueError):
    """A raw scan file is missing, malformed or inconsistent (the message names file and line)."""


@dataclass
class ScanHeader:
    """Scan-wide metadata (the first line of a raw scan file).

    Attributes:
        quantity: ``"level_mm"`` (water level, mm) or ``"mass_g"`` (balance under the tank, g).
        ndim: 3 for real objects; 2 for planar simulations, where volumes are areas (mm^2)
            and the tank cross-section is a width (mm).
        tank_cross_section_mm2: free cross-section ``A`` of the tank at the water line, mm^2
            (mm in 2D); ``None`` when unknown (preprocessing then needs it explicitly).
        step_mm: nominal stage step (mm); the per-reading stage positions are authoritative.
        density_g_per_mm3: liquid density, used to turn balance readings into volumes.
        t_start_mm: water line height (mm, object frame) at stage position 0 before any rise,
            when the rig geometry fixes it for every orientation; orientations may override
            it in their ``meta`` (key ``t_start_mm``).
        noise_sigma: standard deviation of the reading noise (quantity's unit) if known;
            orientations may override it in their ``meta`` (key ``noise_sigma``).
        resolution: reading quantum (quantity's unit), if known.
        rig: identity of the rig / simulator that recorded the scan.
        config: the acquisition settings (sensor, timing, ...), free-form JSON.
        metadata: anything else (object name, operator notes, ...), free-form JSON.
        created: ISO 8601 creation time.
    """

    quantity: str = "level_mm"
    ndim: int = 3
    tank_cross_section_mm2: float | None = None
    step_mm: float | None = None
    density_g_per_mm3: float = WATER_DENSITY_G_PER_MM3
    t_start_mm: float | None = None
    noise_sigma: float | None = None
    resolution: float | None = None
    rig: str = "unknown"
    config: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    created: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%S%z"))

    def __post_init__(self) -> None:
        if self.quantity not in QUANTITIES:
            raise ValueError(f"quantity must be one of {sorted(QUANTITIES)}, got {self.quantity!r}")
        if self.ndim not in (2, 3):
            raise ValueError(f"ndim must be 2 or 3, got {self.ndim!r}")
        for name in ("tank_cross_section_mm2", "step_mm"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number or None, got {value!r}")
        if not self.density_g_per_mm3 > 0:
            raise ValueError(f"density_g_per_mm3 must be positive, got {self.density_g_per_mm3!r}")
        _check_start_height(self.t_start_mm, "t_start_mm")
        for name in ("config", "metadata"):
            if not isinstance(getattr(self, name), dict):
                raise ValueError(f"{name} must be a JSON object (name: value), got {getattr(self, name)!r}")
        for name, option in (("resolution", "rig.resolution"), ("noise_sigma", "")):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, numbers.Real) and 0 <= value < np.inf):
                raise ValueError(f"{name} (the readings' {'quantum' if name == 'resolution' else 'noise'}, in their "
                                 f"unit{'; scan.py: ' + option if option else ''}) must be a number >= 0 or null, "
                                 f"got {value!r}")

    @property
    def units(self) -> dict[str, str]:
        """Units of every recorded field."""
        return {"stage": "mm", "value": QUANTITIES[self.quantity], "time": "s", "angles": "deg",
                "tank_cross_section": "mm^2" if self.ndim == 3 else "mm"}

    def to_json(self) -> dict[str, Any]:
        """The header line's JSON object."""
        return {"type": "header", "format": FORMAT_NAME, "version": FORMAT_VERSION, **asdict(self),
                "units": self.units}

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> "ScanHeader":
        """Inverse of :meth:`to_json` (raises ``ValueError`` / ``TypeError`` on bad content)."""
        if obj.get("format") != FORMAT_NAME:
            raise ValueError(f"not a dipnet raw scan (format={obj.get('format')!r})")
        if obj.get("version") != FORMAT_VERSION:
            raise ValueError(f"unsupported raw scan format version {obj.get('version')!r}")
        known = set(cls.__dataclass_fields__)
        header = cls(**{k: v for k, v in obj.items() if k in known})
        header.check_quantity(obj.get("units"))
        factors = header.unit_factors(obj.get("units"))
        scaled = {name: getattr(header, name) * factors[field] for name, field in
                  (("tank_cross_section_mm2", "tank_cross_section"), ("step_mm", "stage"),
                   ("noise_sigma", "value"), ("resolution", "value")) if getattr(header, name) is not None}
        return replace(header, **scaled)

    def unit_kinds(self) -> dict[str, str]:
        """The kind of unit (a key of :data:`UNITS`) of every field of :attr:`units`."""
        return {"stage": "length", "value": "length" if self.quantity == "level_mm" else "mass", "time": "time",
                "angles": "angle", "tank_cross_section": "area" if self.ndim == 3 else "length"}

    def unit_factors(self, units: Any) -> dict[str, float]:
        """Factors turning each field of a file's declared ``units`` into dipnet's (:attr:`units`):
        e.g. ``{"stage": "in"}`` gives ``stage: 25.4``; an undeclared field is in dipnet's unit.

        Raises:
            ValueError: ``units`` is not an object, or declares a unit this field cannot be read in.
        """
        if units is None:
            units = {}
        if not isinstance(units, dict):
            raise ValueError(f"units must be an object of field: unit, got {units!r}")
        kinds = self.unit_kinds()
        unknown = sorted(set(units) - set(kinds))
        if unknown:
            raise ValueError(f"units.{unknown[0]}: no such field; units are given for {', '.join(kinds)}")
        factors = {}
        for name, kind in kinds.items():
            unit = units.get(name, self.units[name])
            if unit not in UNITS[kind]:
                other = "length" if kind == "area" else "area"
                hint = (f" ({unit!r} is the unit of a {5 - self.ndim}D tank's section: is the header's ndim="
                        f"{self.ndim} right?)" if name == "tank_cross_section" and unit in UNITS[other] else "")
                raise ValueError(f"units.{name}: unknown unit {unit!r}; {name} is read in one of "
                                 f"{', '.join(UNITS[kind])}{hint}")
            factors[name] = UNITS[kind][unit]
        return factors

    def check_quantity(self, units: dict | None = None) -> None:
        """Raise ``ValueError`` when the stored ``units`` or the sensor in ``config`` contradict
        :attr:`quantity` (e.g. ``mass_g`` over a level sensor's readings)."""
        unit = QUANTITIES[self.quantity]
        kind = self.unit_kinds()["value"]
        if isinstance(units, dict) and "value" in units and units["value"] not in UNITS[kind]:
            raise ValueError(f"quantity {self.quantity!r} is read in {unit} but the header's units say "
                             f"readings are in {units['value']!r}")
        sensor = self.config.get("sensor") if isinstance(self.config, dict) else None
        measured = sensor.get("quantity") if isinstance(sensor, dict) else None
        if measured is not None and measured != self.quantity:
            raise ValueError(f"quantity {self.quantity!r} does not match the recording sensor's "
                             f"quantity {measured!r} (config.sensor)")

    def differences(self, other: "ScanHeader") -> list[str]:
        """The fields that forbid appending a scan with header ``other`` to one with this header,
        as ``"field <this value> -> <other value>"`` (empty: compatible): the header fields, then the
        recorded settings of :data:`RESUME_SETTINGS` that both headers record (a rig's run records
        them in ``config``), named by their scan option."""
        keys = ("quantity", "ndim", "tank_cross_section_mm2", "step_mm", "density_g_per_mm3", "t_start_mm")
        fields_ = [f"{k} {getattr(self, k)!r} -> {getattr(other, k)!r}" for k in keys
                   if getattr(self, k) != getattr(other, k)]
        return fields_ + setting_differences(self.config, other.config)


#: Settings in a header's ``config`` that change what a dip records, so a resumed scan must keep
#: them: ``(dotted key in config, the scan option that sets it)``. A dict-valued key is compared
#: leaf by leaf (``rig_geometry.pivot_mm``). Timing, retries, ports and the sensor's line pattern
#: may change between runs. The fake rig's object (``rig.fake.shape``, recorded under ``scan``) is the
#: thing dipped: another one resumed into the file would mix two objects' dips.
RESUME_SETTINGS: tuple[tuple[str, str], ...] = (
    ("plan.start_mm", "protocol.start_mm"),
    ("plan.stop_mm", "protocol.stop_mm"),
    ("plan.origin_height_mm", "rig.origin_height_mm"),
    ("tank_id", "rig.tank"),  # TANK_CONFIG_KEY: the tank a calibration file is checked against
    ("rig_geometry", "rig.geometry"),  # GEOMETRY_CONFIG_KEY: rig.geometry or rig.calibration's geometry
    ("controller.axes.lower.scale", "rig.controller.axes.lower.scale"),
    ("controller.axes.lower.sign", "rig.controller.axes.lower.sign"),
    ("controller.axes.lower.offset", "rig.controller.axes.lower.offset"),
    ("controller.axes.tilt.scale", "rig.controller.axes.tilt.scale"),
    ("controller.axes.tilt.sign", "rig.controller.axes.tilt.sign"),
    ("controller.axes.tilt.offset", "rig.controller.axes.tilt.offset"),
    ("controller.axes.spin.scale", "rig.controller.axes.spin.scale"),
    ("controller.axes.spin.sign", "rig.controller.axes.spin.sign"),
    ("controller.axes.spin.offset", "rig.controller.axes.spin.offset"),
    ("sensor.kind", "sensor"),
    ("sensor.unit", "sensor.device.unit"),
    ("sensor.scale", "sensor.device.scale"),
    ("sensor.offset", "sensor.device.offset"),
    ("sensor.data_type", "sensor.device.data_type"),
    ("sensor.word_order", "sensor.device.word_order"),
    ("sensor.slave", "sensor.device.slave"),  # a Modbus sensor's device and register: another one reads another value
    ("sensor.address", "sensor.device.address"),
    ("scan.rig.fake.shape", "rig.fake.shape"),
)
_UNRECORDED = object()


def _recorded(config: Any, key: str) -> Any:
    """The value at dotted ``key`` of a header's ``config``, or ``_UNRECORDED``."""
    node = config
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return _UNRECORDED
        node = node[part]
    return node


def _leaves(value: Any, key: str) -> dict[str, Any]:
    """``{dotted key: value}`` of every leaf of ``value`` (itself if it is not a dict)."""
    if not isinstance(value, dict):
        return {key: value}
    return {k: v for name, child in value.items() for k, v in _leaves(child, f"{key}.{name}").items()}


def setting_differences(recorded: dict, new: dict) -> list[str]:
    """The settings of :data:`RESUME_SETTINGS` that differ between two headers' ``config``, as
    ``"option (config.key) <recorded> -> <new>"``; a setting one of them does not record is not compared."""
    found = []
    for key, option in RESUME_SETTINGS:
        old_value, new_value = _recorded(recorded, key), _recorded(new, key)
        if old_value is _UNRECORDED or new_value is _UNRECORDED:
            continue
        old_leaves, new_leaves = _leaves(old_value, key), _leaves(new_value, key)
        for leaf in sorted(set(old_leaves) | set(new_leaves)):
            before, after = old_leaves.get(leaf), new_leaves.get(leaf)
            if before != after:
                name = option + leaf[len(key):]
                found.append(f"{name} (config.{leaf}) {before!r} -> {after!r}")
    return found


def _check_start_height(value: Any, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` (a water line height, mm) is a finite number or
    ``None`` (unknown): a string, list or NaN would fail deep in the preprocessing without naming the field."""
    if value is not None and not (isinstance(value, numbers.Real) and np.isfinite(value)):
        raise ValueError(f"{name} (the water line's height at stage 0, mm) must be a finite number or null, "
                         f"got {value!r}")


@dataclass
class OrientationScan:
    """The readings of one orientation.

    Attributes:
        k: orientation index (file order).
        direction: unit "up" vector in the object frame, ``(ndim,)`` float64, or ``None`` when
            only rig angles are known (then :attr:`unit_direction` derives it).
        tilt_deg, spin_deg: rig angles (degrees), see :func:`~dipnet.core.orientations.rig_to_direction`.
        meta: per-orientation metadata (e.g. ``t_start_mm``, ``noise_sigma``).
        stage_mm: commanded stage positions, ``(n,)`` float64, mm, increasing = lowered.
        values: sensor readings, ``(n,)`` float64, unit of the header's quantity.
        time_s: reading times, ``(n,)`` float64, s.
        flags: per-reading flag lists, length ``n``.
        complete: whether the orientation's ``complete`` record was written.
    """

    k: int
    direction: np.ndarray | None = None
    tilt_deg: float | None = None
    spin_deg: float | None = None
    meta: dict = field(default_factory=dict)
    stage_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    flags: list[list[str]] = field(default_factory=list)
    complete: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.meta, dict):
            raise ValueError(f"orientation {self.k}: meta must be a JSON object (name: value), got {self.meta!r}")
        _check_start_height(self.meta.get("t_start_mm"), f"orientation {self.k}: meta.t_start_mm")
        noise = self.meta.get("noise_sigma")
        if noise is not None and not (isinstance(noise, numbers.Real) and 0 <= noise < np.inf):
            raise ValueError(f"orientation {self.k}: meta.noise_sigma (the readings' noise, in their unit) must be a "
                             f"number >= 0 or null, got {noise!r}")
        if self.direction is not None:
            self.direction = np.asarray(self.direction, dtype=np.float64).reshape(-1)
        elif self.tilt_deg is None or self.spin_deg is None:
            raise ValueError(f"orientation {self.k}: give a direction or both tilt_deg and spin_deg")
        self.stage_mm = np.asarray(self.stage_mm, dtype=np.float64).reshape(-1)
        self.values = np.asarray(self.values, dtype=np.float64).reshape(-1)
        self.time_s = np.asarray(self.time_s, dtype=np.float64).reshape(-1)
        if not self.flags:
            self.flags = [[] for _ in range(len(self.stage_mm))]
        n = len(self.stage_mm)
        if not (len(self.values) == len(self.time_s) == len(self.flags) == n):
            raise ValueError(f"orientation {self.k}: stage_mm, values, time_s and flags differ in length")

    @property
    def n_readings(self) -> int:
        return len(self.stage_mm)

    @property
    def unit_direction(self) -> np.ndarray:
        """The unit "up" vector, ``(ndim,)`` float64 (from the rig angles if no direction was given)."""
        if self.direction is not None:
            return self.direction / np.linalg.norm(self.direction)
        return rig_to_direction(self.tilt_deg, self.spin_deg)[0].numpy()

    def orientation_json(self) -> dict[str, Any]:
        """The ``orientation`` line's JSON object."""
        return {"type": "orientation", "k": self.k,
                "direction": None if self.direction is None else self.direction.tolist(),
                "tilt_deg": self.tilt_deg, "spin_deg": self.spin_deg, "meta": self.meta}

    def _append(self, stage_mm: float, value: float, time_s: float, flags: list[str]) -> None:
        self.stage_mm = np.append(self.stage_mm, float(stage_mm))
        self.values = np.append(self.values, float(value))
        self.time_s = np.append(self.time_s, float(time_s))
        self.flags.append(list(flags))


@dataclass
class RawScan:
    """A whole raw scan: header plus orientations (in memory; :meth:`save` writes the file).

    Attributes:
        header: scan-wide metadata.
        orientations: per-orientation readings, in acquisition order.
        truncated: the file it was read from ended with a truncated line (a crash mid-write).
        path: the file it was read from, if any.
        sessions: one dict per rig run that wrote to the file (``session`` records: the first
            orientation it scanned, the time, the controller's and the sensor's identity read after
            connecting, e.g. the firmware version), in file order.
        units: the units the file declared (its header's ``units``); the values in memory are
            converted to dipnet's units (:attr:`ScanHeader.units`).
    """

    header: ScanHeader
    orientations: list[OrientationScan] = field(default_factory=list)
    truncated: bool = False
    path: Path | None = None
    sessions: list[dict[str, Any]] = field(default_factory=list)
    units: dict[str, str] = field(default_factory=dict)

    def complete_orientations(self) -> list[int]:
        """Indices ``k`` of the orientations whose scan finished, in file order."""
        return [o.k for o in self.orientations if o.complete]

    def next_orientation(self) -> int:
        """Index at which an interrupted scan resumes: one past the last complete orientation."""
        done = self.complete_orientations()
        return max(done) + 1 if done else 0

    def completed(self) -> list[OrientationScan]:
        """The complete orientations, in file order."""
        return [o for o in self.orientations if o.complete]

    def directions(self, complete_only: bool = True) -> torch.Tensor:
        """Unit directions ``(K, ndim)`` float64 of the (complete) orientations."""
        scans = self.completed() if complete_only else self.orientations
        if not scans:
            return torch.zeros(0, self.header.ndim, dtype=torch.float64)
        return torch.from_numpy(np.stack([o.unit_direction for o in scans]))

    def without_stated_noise(self) -> RawScan:
        """A copy whose header and orientations state no reading noise (``noise_sigma``): the scan of a sensor
        whose noise nobody gave, as the authors' CSV is (preprocessing then measures it from the readings)."""
        orientations = [replace(o, meta={key: value for key, value in o.meta.items() if key != "noise_sigma"})
                        for o in self.orientations]
        return replace(self, header=replace(self.header, noise_sigma=None), orientations=orientations)

    def save(self, path: str | Path, fsync: bool = False) -> Path:
        """Write the whole scan to ``path`` (overwriting it) in the JSON Lines format."""
        from dipnet.core.rawscan_writer import RawScanWriter  # the writer imports this module

        with RawScanWriter(path, self.header, resume=False, overwrite=True, fsync=fsync) as writer:
            for session in self.sessions:
                writer.record_session(session)
            for o in self.orientations:
                writer.begin_orientation(o.k, direction=o.direction, tilt_deg=o.tilt_deg,
                                         spin_deg=o.spin_deg, meta=o.meta)
                for i in range(o.n_readings):
                    writer.append_reading(o.stage_mm[i], o.values[i], o.time_s[i], o.flags[i])
                if o.complete:
                    writer.complete_orientation()
        return Path(path)


def read_rawscan(path: str | Path) -> RawScan:
    """Read a raw scan file written by :class:`~dipnet.core.rawscan_writer.RawScanWriter`.

    A truncated last line is ignored (``RawScan.truncated`` is set); orientations without a
    ``complete`` record are kept with ``complete=False``. Every other defect raises
    :class:`RawScanFileError` with ``"<path>:<line>: <problem>"``.
    """
    path = Path(path)
    if not path.is_file():
        raise RawScanFileError(f"raw scan file not found: {path}")
    try:
        lines = path.read_bytes().decode("utf-8").split("\n")
    except UnicodeDecodeError as exc:
        raise RawScanFileError(f"{path}: not a UTF-8 text file ({exc})") from exc
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise RawScanFileError(f"{path}: empty file, expected a raw scan header line")
    scan: RawScan | None = None
    by_k: dict[int, OrientationScan] = {}
    clock_back: list[tuple[int, int, float, float]] = []  # (line, orientation, time, time before) (s)
    for lineno, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        try:
            obj = json.loads(text, object_pairs_hook=unique_keys)
        except DuplicateKeyError as exc:  # the last value was read silently: another tank section, level, stage
            raise RawScanFileError(f"{path}:{lineno}: {exc}") from exc
        except json.JSONDecodeError as exc:
            if lineno == len(lines) and scan is not None:
                scan.truncated = True  # a crash mid-write: the last line is cut short
                break
            if lineno == len(lines):  # the only line: a header cut short (a scan stopped as it began?)
                raise RawScanFileError(f"{path}:{lineno}: its only line is not valid JSON ({exc.msg}): a raw scan "
                                       "header cut short (a scan stopped as it began?) holds no reading; delete the "
                                       "file to scan afresh, or give the right file") from exc
            raise RawScanFileError(f"{path}:{lineno}: not valid JSON ({exc.msg})") from exc
        try:
            if not isinstance(obj, dict) or "type" not in obj:
                raise ValueError("expected a JSON object with a 'type' field")
            kind = obj["type"]
            if scan is None:
                if kind != "header":
                    raise ValueError(f"the first line must be the header, got type {kind!r}")
                scan = RawScan(header=ScanHeader.from_json(obj), path=path, units=dict(obj.get("units") or {}))
                factors = scan.header.unit_factors(obj.get("units"))
            elif kind == "orientation":
                k = _index(obj)
                if k in by_k and by_k[k].complete:
                    raise ValueError(f"orientation {k} is begun again after it was completed")
                tilt, spin = (None if obj.get(key) is None else _reading_number(obj, key) * factors["angles"]
                              for key in ("tilt_deg", "spin_deg"))
                direction = obj.get("direction")
                if direction is not None and (not isinstance(direction, list) or not all(
                        is_real(v) for v in direction)):
                    raise ValueError(f"direction must be a list of numbers, got {direction!r}")  # ["1", 0, 0] read
                for key, angle in (("tilt_deg", tilt), ("spin_deg", spin)):
                    if angle is not None and not np.isfinite(angle):  # NaN gave a NaN direction, unsaid
                        raise ValueError(f"{key} must be a finite number, got {obj[key]!r}")
                o = OrientationScan(k=k, direction=obj.get("direction"), tilt_deg=tilt, spin_deg=spin,
                                    meta=obj.get("meta") or {})
                if o.direction is not None and o.direction.shape != (scan.header.ndim,):
                    raise ValueError(f"direction must have {scan.header.ndim} components")
                _check_direction(o)
                scan.orientations = [x for x in scan.orientations if x.k != k] + [o]
                by_k[k] = o
            elif kind == "reading":
                o = _open_orientation(by_k, obj)
                values = [_reading_number(obj, key) * factors[field] for key, field in
                          (("stage_mm", "stage"), ("value", "value"), ("time_s", "time"))]
                if not all(np.isfinite(values)):
                    raise ValueError("reading holds a non-finite number")
                if o.n_readings and values[0] < o.stage_mm[-1]:
                    raise ValueError(f"orientation {o.k}: stage {values[0]:g} mm after {o.stage_mm[-1]:g} mm: "
                                     "the stage moved backwards (readings out of order?)")
                if o.n_readings and values[2] < o.time_s[-1]:
                    clock_back.append((lineno, o.k, values[2], float(o.time_s[-1])))
                flags = obj.get("flags", [])
                if not isinstance(flags, list):
                    raise ValueError("flags must be a list of strings")
                o._append(*values, [str(f) for f in flags])
            elif kind == "complete":
                o = _open_orientation(by_k, obj)
                if "n_readings" in obj and _reading_number(obj, "n_readings", whole=True) != o.n_readings:
                    raise ValueError(f"orientation {o.k} is marked complete with {obj['n_readings']} "
                                     f"readings but {o.n_readings} were recorded")
                o.complete = True
            elif kind == "session":
                scan.sessions.append({key: value for key, value in obj.items() if key != "type"})
            elif kind == "header":
                raise ValueError("a second header line")
            else:
                raise ValueError(f"unknown record type {kind!r}")
        except (KeyError, TypeError, ValueError) as exc:
            detail = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise RawScanFileError(f"{path}:{lineno}: {detail}") from exc
    assert scan is not None  # the first non-blank line either parses as a header or raised
    _warn_clock_back(path, clock_back)
    _warn_step_mismatch(path, scan)
    return scan


def _warn_clock_back(path: Path, steps: list[tuple[int, int, float, float]]) -> None:
    """Warn, naming the file and the first line, when reading times (s) run backwards within a dip:
    ``steps`` holds ``(line, orientation, time, time before)``. Not refused, unlike a stage that moves
    backwards: the readings themselves may be sound (the runner stamps wall-clock time, which a clock
    adjustment can set back), but a level drift or sensor lag fitted against these times is wrong."""
    if not steps:
        return
    lineno, k, t, before = steps[0]
    dips = sorted({step[1] for step in steps})
    more = (f" ({len(steps)} backward steps in {len(dips)} dip(s): {', '.join(map(str, dips))})"
            if len(steps) > 1 else "")
    warnings.warn(f"{path}:{lineno}: orientation {k}: time {t:g} s after {before:g} s: the reading times run "
                  f"backwards within the dip{more} (a clock set back, or readings edited?); the readings are kept, "
                  "but a level drift or sensor lag fitted against these times is wrong: fix the times, or do not "
                  "fit level_drift_mm_per_s or sensor_lag_s from this recording", stacklevel=3)


#: How far (a fraction) the readings' median stage step may differ from the header's ``step_mm`` unwarned.
STEP_TOLERANCE = 0.1


def _warn_step_mismatch(path: Path, scan: RawScan) -> None:
    """Warn, naming the file, the header's ``step_mm`` and the steps found, when the median of the readings'
    stage steps (mm; within each orientation, repeats left out) differs from the header's ``step_mm`` by more than
    :data:`STEP_TOLERANCE` of it. Not refused: the per-reading stage positions are authoritative and the results
    use them alone, but a disagreement this large means one of the two is in another unit (stage readings in cm?)
    or belongs to another scan."""
    nominal = scan.header.step_mm
    steps = np.concatenate([np.diff(o.stage_mm) for o in scan.orientations] + [np.zeros(0)])
    steps = steps[steps > 0]
    if nominal is None or steps.size == 0:
        return
    found = float(np.median(steps))
    if abs(found - nominal) <= STEP_TOLERANCE * nominal:
        return
    log_and_warn(log, f"{path}: the header's step_mm={nominal:g} mm, but the readings' stage steps are "
                      f"{found:g} mm (median; {float(steps.min()):g} to {float(steps.max()):g} mm): one of the two "
                      "is in another unit (stage readings in cm?) or from another scan; the readings' stage positions "
                      "are used, the header's step is ignored", stacklevel=3)


#: How far (degrees) an orientation's recorded direction may lie from the one its rig angles give.
DIRECTION_TOLERANCE_DEG = 0.5


def _check_direction(o: OrientationScan) -> None:
    """Raise ``ValueError`` when ``o``'s recorded direction has no length or is not finite, or, with
    both rig angles recorded (3D), lies more than :data:`DIRECTION_TOLERANCE_DEG` from the direction
    the angles give (:func:`~dipnet.core.orientations.rig_to_direction`). Preprocessing dips along the
    angles' direction (:func:`dipnet.core.geometry.invert_scan`), so a file whose two disagree (angles
    in another convention or unit, an elevation for a tilt, a hand edit) would be reconstructed from
    directions it does not mean, without a word."""
    if o.direction is None:
        return
    norm = float(np.linalg.norm(o.direction))
    if not np.isfinite(o.direction).all() or norm == 0.0:
        raise ValueError(f"orientation {o.k}: direction {o.direction.tolist()} is not a direction "
                         "(non-finite or of length 0)")
    if o.tilt_deg is None or o.spin_deg is None or o.direction.shape != (3,):
        return
    angles = rig_to_direction(o.tilt_deg, o.spin_deg)[0].numpy()
    off = float(np.degrees(np.arccos(np.clip(o.direction @ angles / norm, -1.0, 1.0))))
    if off > DIRECTION_TOLERANCE_DEG:
        raise ValueError(
            f"orientation {o.k}: its direction {np.round(o.direction / norm, 4).tolist()} is {off:.1f} deg from "
            f"the one its rig angles give (tilt {o.tilt_deg:g} deg, spin {o.spin_deg:g} deg: "
            f"{np.round(angles, 4).tolist()}); the record contradicts itself (angles in another convention "
            "or unit, an elevation for a tilt?) and dipnet dips along the angles: correct one of them, "
            "or drop tilt_deg and spin_deg to use the direction")


@contextmanager
def naming_file(path: str | Path) -> Iterator[None]:
    """Re-raise a ``ValueError`` whose message lacks ``path`` as :class:`RawScanFileError`
    ``"<path>: <message>"``, so every error about a recording names its file."""
    try:
        yield
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise RawScanFileError(f"{path}: {exc}") from exc


#: The lowest plausible water level in mm: a tank's water stands tens to hundreds of mm high.
MIN_LEVEL_MM = 1.0


def check_level_unit(raw: RawScan, column: str) -> None:
    """Raise :class:`RawScanFileError` when the water levels of ``raw`` (quantity ``level_mm``)
    cannot be millimetres: every level below :data:`MIN_LEVEL_MM` (a level in metres, 0.19 for
    190 mm, rising by hundredths). The message names the file, the ``column`` and the likely unit."""
    levels = [o.values for o in raw.orientations if o.n_readings]
    if raw.header.quantity != "level_mm" or not levels:
        return
    peak = float(max(np.abs(v).max() for v in levels))
    if peak >= MIN_LEVEL_MM:
        return
    rise = float(max(v.max() - v.min() for v in levels))
    quantum = raw.header.resolution
    below = f", below the sensor resolution {quantum:g} mm" if quantum and rise < quantum else ""
    raise RawScanFileError(f"{raw.path}: column {column}: the water levels are at most {peak:.3g} mm and rise by "
                           f"at most {rise:.3g} mm{below}: not millimetres; they look like metres "
                           f"({peak * 1000:.4g} mm): convert them to mm (or declare the unit)")


def check_reading_sign(raw: RawScan, column: str) -> None:
    """Raise :class:`RawScanFileError` when the readings of ``raw`` fall as the object is lowered in most of its
    complete dips (the median of each dip's last three readings below that of its first three): a lowered object
    displaces water, so a level (or a balance's reading) rises; one that falls was counted downwards, or its sign
    reversed.
    A cavity flooding or a leak makes some dips fall, never most by their end. The message names the file and the
    ``column``. Before, each dip was rejected for its "outliers", and then the scan for having no dip left."""
    dips = [o.values for o in raw.orientations if o.complete and o.n_readings >= 6]  # a live dip may not rise yet
    net = np.array([np.median(v[-3:]) - np.median(v[:3]) for v in dips])
    if not len(net) or (net < 0).sum() <= len(net) / 2:
        return
    raise RawScanFileError(f"{raw.path}: column {column}: the reading falls as the object is lowered in "
                           f"{int((net < 0).sum())} of {len(net)} dips (by a median {-float(np.median(net)):.4g}), "
                           "where displaced water raises it: is its sign reversed (a level counted downwards, "
                           "a distance sensor read as a level)? Negate it")


def complete_dips(raw: RawScan) -> list[OrientationScan]:
    """The complete orientations of ``raw``, warning about the ones left out.

    An orientation without its ``complete`` record (an interrupted scan, or a truncated last
    line cut off by a crash) is dropped with a warning naming it. Raises
    :class:`RawScanFileError` when no orientation is complete.
    """
    where = "the raw scan" if raw.path is None else f"scan {raw.path}"
    done = raw.completed()
    dropped = [o.k for o in raw.orientations if not o.complete]
    if dropped:
        cause = " (its last line is truncated: a crash mid-write?)" if raw.truncated else ""
        message = f"{where}{cause}: orientation(s) {dropped} are incomplete and left out"
        log_and_warn(log, message, stacklevel=2)
    if not done:
        raise RawScanFileError(f"{where} holds no complete dip ({len(raw.orientations)} orientation(s) "
                               f"begun, {sum(o.n_readings for o in raw.orientations)} reading(s))")
    return done


def _index(obj: dict) -> int:
    """A record's orientation index ``k``: a whole number (``0.5`` was read as 0; a string index ``"1"`` reads)."""
    k = obj["k"]
    if isinstance(k, bool) or (isinstance(k, numbers.Real) and not float(k).is_integer()):
        raise ValueError(f"orientation index k must be a whole number, got {k!r}")
    return int(k)


def _reading_number(obj: dict, key: str, whole: bool = False) -> float:
    """A record's number ``key`` (a reading's ``stage_mm``, ``value``, ``time_s``; an orientation's ``tilt_deg``,
    ``spin_deg``; a ``complete`` record's ``n_readings``, ``whole``): a JSON number (``"0"``, a string, was read
    as 0; ``"10"`` degrees as 10; ``87.5`` readings as 87)."""
    value = obj[key]
    if not is_real(value) or (whole and not float(value).is_integer()):
        raise ValueError(f"{key} must be a {'whole ' if whole else ''}number, got {value!r}")
    return float(value)


def _open_orientation(by_k: dict[int, OrientationScan], obj: dict) -> OrientationScan:
    k = _index(obj)
    if k not in by_k:
        raise ValueError(f"record for orientation {k}, which was never begun")
    if by_k[k].complete:
        raise ValueError(f"record for orientation {k} after it was completed")
    return by_k[k]
