"""Rig calibration files: one :class:`~dipnet.core.geometry.RigGeometry` with the rig and tank it belongs to.

Format (YAML or JSON by suffix, version 2; version 1 files, without ``intervals_90`` and
``not_estimated``, are read too)::

    format: dipnet.rig_calibration
    version: 2
    rig: fake-grbl            # the rig's identity, as scans record it (ScanHeader.rig)
    tank: lab-tank-1          # the tank's identity (scans record it as header.config["tank_id"])
    method: reference         # reference | self | manual
    created: 2026-11-23T11:00:00+0000
    geometry:                 # every RigGeometry field; cross_section_mm2 omitted = the scan's nominal
      pivot_mm: 20.1
      tilt_axis_offset_mm: 14.8
      tilt_zero_deg: 1.02
      spin_zero_deg: 0.0
      step_scale: 1.0
      cross_section_mm2: 55210.0
      level_drift_mm_per_s: 0.0
      sensor_lag_s: 0.0
    uncertainty: {pivot_mm: 0.3}   # standard errors of the estimated fields, same units ({} if none)
    intervals_90: {pivot_mm: [19.6, 20.6]}   # 90% intervals of the estimated fields ({} if none)
    not_estimated:                 # fields holding configured values, with the reason ({} if none)
      spin_zero_deg: "a ball centred on the spin axis looks the same at every spin"
    notes: ball d=60 mm at 7 orientations
    reference_centroid_mm: [24.9, 0.0, 0.05]   # optional: where a reference calibration fitted its ball's centre
                                               # (object frame, mm; its distance from the spin axis is fitted)

A version 2 file names every section but ``reference_centroid_mm`` and every geometry field but
``cross_section_mm2`` (as :func:`save_calibration` writes it): one without them (a truncated file)
is refused, naming the missing keys, rather than read with ideal values in their place. Version 1 files may omit
geometry fields (ideal) and the optional sections.

A field of ``geometry`` that is listed under ``not_estimated`` is the configured value, not an
estimate; with ``method: reference`` or ``self`` every other field given was estimated.

:func:`load_calibration` validates everything and raises :class:`CalibrationFileError` (a
``ValueError``) naming the file and the cause: unknown keys, a key given twice, wrong format or version,
unphysical values, or a rig / tank other than the one it is used for. It is never used
silently: :func:`check_identity` compares it with the scan it is applied to.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Hashable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from dipnet.core.rawscan import ScanHeader
from dipnet.core import strict_json
from dipnet.core.atomic_write import write_atomically
from dipnet.core.geometry import GeometryError, RigGeometry

FORMAT_NAME = "dipnet.rig_calibration"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
METHODS = ("reference", "self", "manual")
_KEYS = {"format", "version", "rig", "tank", "method", "created", "geometry", "uncertainty", "intervals_90",
         "not_estimated", "notes", "reference_centroid_mm"}
_OPTIONAL_KEYS = {"reference_centroid_mm"}  # written by reference calibrations off the spin axis only
_OPTIONAL_GEOMETRY = {"cross_section_mm2"}  # omitted when the scan's nominal section is meant
TANK_CONFIG_KEY = "tank_id"  # ScanHeader.config key holding the tank's identity


class CalibrationFileError(ValueError):
    """A calibration file is missing, malformed, unphysical or belongs to another rig or tank."""


@dataclass(frozen=True)
class Calibration:
    """A rig geometry with the identity of the rig and tank it was measured on.

    Attributes:
        geometry: the calibrated geometry.
        rig: the rig's identity (matches :attr:`ScanHeader.rig`).
        tank: the tank's identity (matches ``ScanHeader.config["tank_id"]`` when a scan records it).
        method: how it was obtained: ``reference`` | ``self`` | ``manual``.
        uncertainty: standard errors per estimated geometry field (same units), if known.
        intervals: 90% intervals ``(low, high)`` per estimated geometry field.
        not_estimated: geometry field -> why it holds the configured value, not an estimate.
        notes: free text.
        reference_centroid_mm: where a reference calibration fitted its object's centre ``(x, y, z)``
            (object frame, mm; its distance from the spin axis is fitted), ``None`` if not.
        created: ISO 8601 time.
    """

    geometry: RigGeometry
    rig: str
    tank: str
    method: str = "manual"
    uncertainty: dict[str, float] = field(default_factory=dict)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    not_estimated: dict[str, str] = field(default_factory=dict)
    notes: str = ""
    reference_centroid_mm: tuple[float, float, float] | None = None
    created: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%S%z"))

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT_NAME, "version": FORMAT_VERSION, "rig": self.rig, "tank": self.tank,
                "method": self.method, "created": self.created,
                "geometry": {k: v for k, v in self.geometry.to_dict().items() if v is not None},
                "uncertainty": {k: float(v) for k, v in self.uncertainty.items()},
                "intervals_90": {k: [float(v[0]), float(v[1])] for k, v in self.intervals.items()},
                "not_estimated": {k: str(v) for k, v in self.not_estimated.items()}, "notes": self.notes,
                **({} if self.reference_centroid_mm is None
                   else {"reference_centroid_mm": [float(v) for v in self.reference_centroid_mm]})}


def keep_previous(path: str | Path) -> Path | None:
    """Rename an existing file ``path`` to ``<stem>.<its modification time><suffix>`` beside it (``-1``, ``-2``, ...
    added while that name is taken), so that writing a new calibration there loses no earlier one (another rig's or
    tank's, or the last good one). Returns the new name, or ``None`` when ``path`` is no file."""
    path = Path(path)
    if not path.is_file():
        return None
    stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(path.stat().st_mtime))
    kept, n = path.with_name(f"{path.stem}.{stamp}{path.suffix}"), 0
    while kept.exists():
        n += 1
        kept = path.with_name(f"{path.stem}.{stamp}-{n}{path.suffix}")
    path.rename(kept)
    return kept


def save_calibration(calibration: Calibration, path: str | Path) -> Path:
    """Write ``calibration`` to ``path`` (``.json``, else YAML); returns the path.

    The file is written whole or not at all: a temporary file beside it, flushed to disk, renamed over ``path``, so a
    run killed mid-write leaves the previous file (or none), never one cut short (a YAML file cut in its last section
    read without a word, its fitted ball centre ``reference_centroid_mm`` or its notes cut)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = calibration.to_dict()
    text = strict_json.dumps(data, indent=2) if path.suffix.lower() == ".json" \
        else yaml.safe_dump(data, sort_keys=False)
    return write_atomically(path, lambda stream: stream.write(text))


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.safe_load`` refusing a mapping that names a key twice (:func:`~dipnet.core.strict_json.unique_keys`):
    it keeps the last silently, so a hand-edit that adds ``pivot_mm: 0.0`` below ``pivot_mm: 188.0`` read the scan
    with a pivot of 0."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):  # the keys as written (a merge ``<<`` may override its keys)
            written = [(self.construct_object(k, deep=True), v.value if isinstance(v, yaml.ScalarNode) else "...")
                       for k, v in node.value if k.tag != "tag:yaml.org,2002:merge"]
            strict_json.unique_keys([(k, v) for k, v in written if isinstance(k, Hashable)])
        return super().construct_mapping(node, deep=deep)


def load_calibration(path: str | Path, rig: str | None = None, tank: str | None = None) -> Calibration:
    """Read and validate a calibration file; ``rig`` / ``tank``, when given, must match its identity."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"calibration file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text, object_pairs_hook=strict_json.unique_keys) if path.suffix.lower() == ".json" \
            else yaml.load(text, Loader=_UniqueKeyLoader)
    except (UnicodeDecodeError, json.JSONDecodeError, yaml.YAMLError, strict_json.DuplicateKeyError) as exc:
        raise CalibrationFileError(f"{path}: not a readable calibration file ({' '.join(str(exc).split())})") from exc
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{path}: expected a mapping with format {FORMAT_NAME!r}")
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise CalibrationFileError(f"{path}: unknown key(s) {unknown}; known: {sorted(_KEYS)}")
    if data.get("format") != FORMAT_NAME:
        raise CalibrationFileError(f"{path}: not a rig calibration (format={data.get('format')!r})")
    if isinstance(data.get("version"), bool) or data.get("version") not in READ_VERSIONS:  # true == 1 to Python
        raise CalibrationFileError(f"{path}: unsupported calibration version {data.get('version')!r}")
    for key in ("rig", "tank"):
        if not isinstance(data.get(key), str) or not data[key].strip():
            raise CalibrationFileError(f"{path}: '{key}' must name the {key} the calibration belongs to")
    if data.get("method", "manual") not in METHODS:
        raise CalibrationFileError(f"{path}: method must be one of {METHODS}, got {data.get('method')!r}")
    if not isinstance(data.get("geometry"), dict):
        raise CalibrationFileError(f"{path}: 'geometry' must be a mapping of rig geometry values")
    try:
        geometry = RigGeometry.from_dict(data["geometry"])
        uncertainty = {k: _number(v) for k, v in _section(data, "uncertainty").items()}
        for name, sd in uncertainty.items():
            if sd < 0:  # NaN (null) is unknown
                raise ValueError(f"uncertainty.{name}={sd:g}: a standard error is >= 0 (null if unknown)")
        intervals = {}
        for name, pair in _section(data, "intervals_90").items():
            if not isinstance(pair, (list, tuple)) or len(pair) != 2:
                raise ValueError(f"intervals_90.{name} must be [low, high] in the field's units, got {pair!r}")
            intervals[name] = (_number(pair[0]), _number(pair[1]))
        not_estimated = {k: str(v) for k, v in _section(data, "not_estimated").items()}
        for name, (low, high) in intervals.items():  # a hand-edited interval that cannot hold its estimate
            value = getattr(geometry, name, None)
            if math.isnan(low) or math.isnan(high):  # unknown (written as null)
                continue
            if not low <= high or (isinstance(value, float) and not low <= value <= high):
                raise ValueError(f"intervals_90.{name}: [{low:g}, {high:g}] does not hold the estimate "
                                 f"geometry.{name}={value}")
        centroid = data.get("reference_centroid_mm")
        if centroid is not None and len(centroid) != 3:
            raise ValueError(f"reference_centroid_mm must be [x, y, z] (mm), got {centroid!r}")
        centroid = None if centroid is None else tuple(_number(v) for v in centroid)
    except (GeometryError, TypeError, ValueError, IndexError, KeyError, AttributeError) as exc:
        raise CalibrationFileError(f"{path}: {exc}") from exc
    missing = _missing_keys(data)
    if missing:
        raise CalibrationFileError(f"{path}: missing key(s) {missing}: a version {data['version']} calibration file "
                                   "names every one (is it truncated?)")
    calibration = Calibration(geometry=geometry, rig=data["rig"], tank=data["tank"],
                              method=data.get("method", "manual"), uncertainty=uncertainty,
                              intervals=intervals, not_estimated=not_estimated,
                              notes=str(data.get("notes") or ""), reference_centroid_mm=centroid,
                              created=str(data.get("created") or ""))
    check_identity(calibration, rig, tank, source=str(path))
    return calibration


def _missing_keys(data: dict[str, Any]) -> list[str]:
    """The sections and ``geometry.<field>`` keys a version 2 file lacks (none for version 1)."""
    if data["version"] == 1:
        return []
    required = {f.name for f in fields(RigGeometry)} - _OPTIONAL_GEOMETRY
    return sorted(_KEYS - _OPTIONAL_KEYS - set(data)) + [f"geometry.{name}"
                                                         for name in sorted(required - set(data["geometry"]))]


def _section(data: dict[str, Any], key: str) -> dict[str, Any]:
    """The mapping ``data[key]`` (``uncertainty``, ``intervals_90``, ``not_estimated``; missing or null: empty), keyed
    by rig geometry fields: another key (a typo, ``pivot`` for ``pivot_mm``) was kept unread, unchecked."""
    section = data.get(key) or {}
    if not isinstance(section, dict):
        raise ValueError(f"'{key}' must be a mapping of rig geometry fields, got {type(section).__name__} {section!r}")
    known = [f.name for f in fields(RigGeometry)]
    unknown = sorted(str(k) for k in section if k not in known)
    if unknown:
        raise ValueError(f"unknown rig geometry key(s) {unknown} in '{key}'; known: {known}")
    return section


def _number(value: Any) -> float:
    """A number of the file; ``null`` (how strict JSON writes a non-finite one) reads as NaN: unknown. A boolean
    is refused (``float(True)`` is 1.0: ``[true, 0, 0]`` was read as a centre at x = 1 mm)."""
    if isinstance(value, bool):
        raise ValueError(f"expected a number or null, got {value!r}")
    return math.nan if value is None else float(value)


def check_identity(calibration: Calibration, rig: str | None, tank: str | None, source: str = "calibration") -> None:
    """Raise :class:`CalibrationFileError` when ``rig`` / ``tank`` (if given) differ from the calibration's."""
    if rig is not None and rig != calibration.rig:
        raise CalibrationFileError(f"{source}: calibrated on rig {calibration.rig!r}, not on {rig!r}")
    if tank is not None and tank != calibration.tank:
        raise CalibrationFileError(f"{source}: calibrated on tank {calibration.tank!r}, not on {tank!r}")


def scan_tank(header: ScanHeader) -> str | None:
    """The tank a scan records: ``header.config["tank_id"]``, or for scans recorded before ``scan.py``
    wrote it there, the scan config's ``rig.tank``; ``None`` when it names none."""
    tank = header.config.get(TANK_CONFIG_KEY)
    if tank is None:
        scan = header.config.get("scan")
        rig = scan.get("rig") if isinstance(scan, dict) else None
        tank = rig.get("tank") if isinstance(rig, dict) else None
    return None if tank is None else str(tank)


def scan_calibration(path: str | Path, header: ScanHeader) -> Calibration:
    """Load the calibration at ``path`` for a scan: its rig must be the scan's, and its tank the
    scan's when the scan records one (:func:`scan_tank`)."""
    return load_calibration(path, rig=header.rig, tank=scan_tank(header))
