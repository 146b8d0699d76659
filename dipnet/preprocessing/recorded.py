"""From recordings to measurements: readers and the real-data steps of the paper's section 5.2.

Readers
-------
* :func:`read_scan`: dipnet's own raw scan files (:func:`dipnet.core.rawscan.read_rawscan`), or
  the CSV of the authors' robot (:func:`read_authors_csv`, columns
  ``SN,R1_deg,R2_deg,Height_mm,WaterLevel_mm``; R1 = tilt, R2 = spin, Height decreasing as the
  object goes down), both as a :class:`~dipnet.core.rawscan.RawScan`.

Real-data steps (used by :func:`read_raw_recording`, behind ``source=recorded``)
--------------------------------------------------------------------------------
1. fixture subtraction (:func:`subtract_fixture`) when a fixture-only recording is given;
2. truncated dips (the object still going under when the scan stopped) are detected
   (:func:`truncated_orientations`) and kept or dropped;
3. the rig geometry (:mod:`dipnet.core.geometry`): a calibration file or explicit values
   (pivot, tilt-axis offset, zero offsets, cross-section, ...) map the readings to true
   directions, stage travel and levels (:func:`~dipnet.core.geometry.invert_scan`); the start
   height of each dip is ``t0 + p (cos r - 1) + e sin r``, with ``t0`` from the recording or,
   when it does not know it (the authors' CSV), placed by :func:`geometry_start_heights`;
4. rise -> volume with the tank cross-section, non-uniform -> uniform slabs and (optionally) the 5-tap
   Gaussian smoothing (:func:`dipnet.preprocessing.preprocess.preprocess`);
5. symmetry exploitation (:func:`dipnet.preprocessing.symmetry.expand_symmetry`, for any source):
   every profile is copied to the directions a declared symmetry group (n-fold rotation about z,
   optionally with mirror planes: D3 for the three cats) maps it to; coinciding directions are merged
   (averaged);
6. interpolation of missing orientations (:func:`interpolate_orientations`);
plus :func:`calibrate_cross_section` (the tank cross-section from a dip of a reference object
of known volume).
"""

from __future__ import annotations

import codecs
import csv
import io
import logging
import math
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from dipnet.core.counts import is_real, whole_number
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.keywords import forwards_to
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.core.warn import log_and_warn
from dipnet.preprocessing.preprocess import level_drift_removed, preprocess, repair_without_drift
from dipnet.core.rawscan import (OrientationScan, RawScan, RawScanFileError, ScanHeader, check_level_unit,
                                 check_reading_sign, complete_dips, read_rawscan)
from dipnet.preprocessing.readings import max_object_section
from dipnet.core.calibration_file import scan_calibration
from dipnet.core.geometry import RigGeometry, as_geometry, invert_scan, scan_geometry
from dipnet.preprocessing.symmetry import apply_symmetry, expand_symmetry, symmetry_group  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

AUTHORS_COLUMNS = ("SN", "R1_deg", "R2_deg", "Height_mm", "WaterLevel_mm")
AUTHORS_TANK_MM2 = 540.0 * 340.0  # the authors' value for the 3 mm cats recording
AUTHORS_QUANTUM_MM = 0.04
#: How close (mm) every level must lie to a multiple of :data:`AUTHORS_QUANTUM_MM` for a CSV to be read as the
#: authors' sensor's (its file prints two decimals: every value is a multiple of 0.04 mm, up to rounding).
AUTHORS_QUANTUM_TOL_MM = 1e-6


# ============================================================================ readers
def _csv_text(path: Path) -> str:
    """The text of a CSV file: ASCII / UTF-8, with or without the byte-order mark spreadsheet
    programs write first (UTF-8 ``EF BB BF``, or UTF-16 as Excel's "Unicode text"); a byte that
    does not decode shows as U+FFFD in the error messages."""
    data = path.read_bytes()
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return data.decode("utf-16", errors="replace")
    return data.decode("utf-8-sig", errors="replace")


def read_authors_csv(path: str | Path, tank_cross_section_mm2: float = AUTHORS_TANK_MM2) -> RawScan:
    """The authors' robot CSV as a raw scan.

    The file may start with a byte-order mark (spreadsheet programs write one). Rows are grouped
    into orientations by consecutive equal ``(R1, R2)``; ``stage_mm =
    -Height_mm`` (increasing = lowered), ``values`` = water level (mm), tilt = R1, spin = R2.
    Every orientation is complete but a last one that ends above every other's deepest height (a file cut off
    mid-dip: :func:`_last_dip_cut_short`); times are unknown (the row index is stored as time). The reading
    quantum is the authors' 0.04 mm when every level is a multiple of it, else unknown (:func:`authors_quantum`).

    Raises:
        RawScanFileError: missing file, wrong columns, non-numeric or non-finite values, a
            height that goes up within a dip (message names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise RawScanFileError(f"CSV file not found: {path}")
    rows = list(csv.reader(io.StringIO(_csv_text(path), newline="")))
    if not rows or tuple(c.strip() for c in rows[0]) != AUTHORS_COLUMNS:
        raise RawScanFileError(f"{path}:1: expected the header {','.join(AUTHORS_COLUMNS)}, "
                               f"got {','.join(rows[0]) if rows else 'an empty file'}")
    data, linenos = [], []
    last = max((i for i, row in enumerate(rows) if row and "".join(row).strip()), default=0) + 1
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) < 5 and lineno == last:  # cut off while it was written, as a .jsonl's last line
            message = f"{path}:{lineno}: the last row is cut off ({len(row)} of 5 fields): dropped"
            log_and_warn(log, message, stacklevel=2)
            continue
        if len(row) != 5:
            raise RawScanFileError(f"{path}:{lineno}: expected 5 fields, got {len(row)}")
        try:
            values = [float(x) for x in row]
        except ValueError as exc:
            raise RawScanFileError(f"{path}:{lineno}: {exc}") from exc
        bad = [i for i, x in enumerate(values) if not math.isfinite(x)]
        if bad:
            raise RawScanFileError(f"{path}:{lineno}: {AUTHORS_COLUMNS[bad[0]]} is not a finite number "
                                   f"({row[bad[0]].strip()})")
        data.append(values)
        linenos.append(lineno)
    if not data:
        raise RawScanFileError(f"{path}: no data rows")
    a = np.asarray(data)
    change = np.flatnonzero(np.any(np.diff(a[:, 1:3], axis=0) != 0, axis=1)) + 1
    blocks = np.split(np.arange(len(a)), change)
    steps_up = [bool((np.diff(a[idx, 3]) > 0).all()) for idx in blocks if len(idx) > 1]
    if steps_up and all(steps_up):
        raise RawScanFileError(f"{path}: Height_mm rises within every dip ({a[blocks[0][0], 3]:g}, "
                               f"{a[blocks[0][1], 3]:g}, ...), where the authors' robot records the stage height, "
                               "which falls as the object is lowered (0, -3, -6, ...): this file counts depth as "
                               "positive; negate its Height_mm column")
    for idx in blocks:  # the object only goes down within a dip: Height_mm never increases
        up = np.flatnonzero(np.diff(a[idx, 3]) > 0)
        if up.size:
            i = idx[up[0] + 1]
            raise RawScanFileError(f"{path}:{linenos[i]}: Height_mm {a[i, 3]:g} after {a[i - 1, 3]:g}: the stage "
                                   "moved backwards within a dip (rows out of order? or the same R1, R2 dipped twice "
                                   "in a row: dips are told apart by their angles)")
    _warn_angles_in_radians(a[:, 1:3], path)
    steps = np.diff(-a[:, 3])[np.diff(-a[:, 3]) > 0]
    header = ScanHeader(
        quantity="level_mm", ndim=3, tank_cross_section_mm2=float(tank_cross_section_mm2),
        step_mm=float(np.median(steps)) if steps.size else None, resolution=authors_quantum(a[:, 4], path),
        rig="Aberman et al. 2017 dipping robot (Kewiee/DipTransform)",
        metadata={"source": str(path), "format": "authors_csv", "columns": list(AUTHORS_COLUMNS)})
    scan = RawScan(header=header, path=path)
    cut = _last_dip_cut_short(a[:, 3], blocks)
    if cut:
        reached = max(a[idx[-1], 3] for idx in blocks[:-1])
        log_and_warn(log, f"{path}:{linenos[-1]}: the last dip ends at Height_mm {a[-1, 3]:g}, short of the "
                          f"{reached:g} or deeper every other dip reaches: the file is cut off mid-dip?", stacklevel=2)
    for k, idx in enumerate(blocks):
        scan.orientations.append(OrientationScan(
            k=k, tilt_deg=float(a[idx[0], 1]), spin_deg=float(a[idx[0], 2]), stage_mm=-a[idx, 3],
            values=a[idx, 4], time_s=a[idx, 0], meta={"rows": [int(a[idx[0], 0]), int(a[idx[-1], 0])]},
            complete=not (cut and k == len(blocks) - 1)))
    return scan


def _warn_angles_in_radians(angles: np.ndarray, path: Path) -> None:
    """Warn when the authors' CSV's ``R1_deg``, ``R2_deg`` columns (``angles`` ``(n, 2)``) look like radians: every
    angle within ``[-2 pi, 2 pi]``, some not whole degrees, more than one direction. Read as degrees they span a few
    degrees only, and the reader ran on (exit 0) with the dips bunched about the vertical."""
    if len(np.unique(angles, axis=0)) < 2 or float(np.abs(angles).max()) > 2 * math.pi:
        return
    if np.allclose(angles, np.round(angles), rtol=0, atol=1e-9):  # whole degrees: a narrow plan, not radians
        return
    r1, r2 = angles[:, 0], angles[:, 1]
    log_and_warn(log, f"{path}: every R1_deg and R2_deg lies within [-2 pi, 2 pi] (R1 {r1.min():g} to {r1.max():g}, "
                      f"R2 {r2.min():g} to {r2.max():g}), and not in whole degrees: angles in radians? They are read "
                      f"as degrees, so the dips tilt {np.abs(r1).max():.3g} deg at most; give the columns in degrees "
                      "(degrees = radians x 180 / pi)", stacklevel=3)


def _last_dip_cut_short(heights: np.ndarray, blocks: list[np.ndarray]) -> bool:
    """Whether the last dip of the authors' CSV (rows ``blocks[-1]`` of ``heights``, ``Height_mm``, falling as the
    object is lowered) ends above the deepest height every other dip reaches: the robot lowers every dip through
    the same travel, so a file cut off on a row boundary leaves a last dip that looks complete, with its volume
    missing (the CSV has no record of a dip's end, as a raw scan's ``complete`` line)."""
    if len(blocks) < 2:
        return False
    return bool(heights[blocks[-1][-1]] > max(heights[idx[-1]] for idx in blocks[:-1]))


def authors_quantum(levels: np.ndarray, path: str | Path) -> float | None:
    """The reading quantum (mm) of an authors'-format CSV's water levels ``levels`` ``(n,)`` (mm): the authors'
    sensor's :data:`AUTHORS_QUANTUM_MM` when every level is a multiple of it, else ``None`` (unknown).

    A quantum the readings do not have misleads every check that weighs it: levels converted to inches under
    ``WaterLevel_mm`` (every volume 25.4**2 times too small) were taken as 0.04 mm readings, coarse against their
    slabs, and the consistency check then named the sensor's resolution as the cause and left out the unit hint.
    """
    steps = np.asarray(levels, dtype=np.float64) / AUTHORS_QUANTUM_MM
    off = float(np.max(np.abs(steps - np.round(steps)))) * AUTHORS_QUANTUM_MM if steps.size else 0.0
    if off <= AUTHORS_QUANTUM_TOL_MM:
        return AUTHORS_QUANTUM_MM
    log.info("%s: the water levels are not multiples of the authors' %g mm reading quantum (up to %.3g mm off): "
             "another sensor, or levels converted from another unit; the reading quantum is left unknown",
             path, AUTHORS_QUANTUM_MM, off)
    return None


def read_scan(path: str | Path, tank_cross_section_mm2: float | None = None) -> RawScan:
    """A dipnet raw scan (``.jsonl``) or an authors' CSV (``.csv``) as a :class:`RawScan`; water levels
    that cannot be mm (:func:`dipnet.core.rawscan.check_level_unit`) and readings that fall as the object is
    lowered (:func:`dipnet.core.rawscan.check_reading_sign`) are refused."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        raw, column = read_authors_csv(path, tank_cross_section_mm2 or AUTHORS_TANK_MM2), AUTHORS_COLUMNS[4]
    else:
        raw, column = read_rawscan(path), "value (of the reading lines)"
        if tank_cross_section_mm2 is not None:
            raw.header = replace(raw.header, tank_cross_section_mm2=float(tank_cross_section_mm2))
    check_level_unit(raw, column)
    check_reading_sign(raw, column)
    return raw


# ============================================================================ helpers
def submerged_volume(o: OrientationScan, scale: float, n_baseline: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """``(stage (n,), V (n,))``: the stage positions (mm) and the submerged volume ``V`` (mm^3,
    made non-decreasing, zero at the first ``n_baseline`` readings' mean) of one orientation;
    ``scale`` turns readings into volumes (``A`` for levels, ``1 / density`` for balances)."""
    values = np.maximum.accumulate(o.values)
    volume = scale * (values - values[:n_baseline].mean())
    return o.stage_mm, np.maximum(volume, 0.0)


def _level_scale(header: ScanHeader, area: float) -> tuple[float, float]:
    """``(reading -> volume factor, area)``."""
    return (area if header.quantity == "level_mm" else 1.0 / header.density_g_per_mm3), area


def truncated_orientations(raw: RawScan, tail_fraction: float = 0.1, tail_tol: float = 0.04) -> list[int]:
    """Orientations ``k`` whose reading still rose at the end of the scan: the rise over the last
    ``tail_fraction`` of the readings exceeds ``tail_tol`` x the total rise."""
    out = []
    for o in raw.orientations:
        v = np.maximum.accumulate(o.values)
        n = max(2, int(round(tail_fraction * len(v))))
        total = v[-1] - v[0]
        if total > 0 and v[-1] - v[-n] > tail_tol * total:
            out.append(o.k)
    return out


def calibrate_cross_section(levels, volume_mm3: float, n_baseline: int = 3, n_plateau: int = 3) -> float:
    """Tank free cross-section (mm^2) from a dip of a reference object of known volume.

    Args:
        levels: water levels (mm) of one full dip, ``(n,)`` (or an :class:`OrientationScan`):
            the first ``n_baseline`` readings with the object clear of the water, the last
            ``n_plateau`` with it fully under (and nothing else going under).
        volume_mm3: the reference volume (e.g. a ball: ``pi d^3 / 6``).

    Returns ``A = V / rise``; the rise is plateau mean minus baseline mean.
    """
    values = np.asarray(levels.values if isinstance(levels, OrientationScan) else levels, dtype=np.float64)
    if values.size < n_baseline + n_plateau:
        raise ValueError(f"need at least {n_baseline + n_plateau} readings, got {values.size}")
    rise = values[-n_plateau:].mean() - values[:n_baseline].mean()
    if not rise > 0:
        raise ValueError(f"the level did not rise ({rise:g} mm): not a dip of the reference object")
    return float(volume_mm3) / rise


def subtract_fixture(raw: RawScan, fixture: RawScan, area: float | None = None, n_baseline: int = 3) -> RawScan:
    """Remove a fixture's contribution from every orientation of ``raw``.

    ``fixture`` is a recording of the fixture alone on the same rig (same stage coordinates);
    each orientation uses the fixture orientation of nearest tilt (then spin). The fixture's
    submerged volume ``F(u)`` is a function of the water line ``u = s + V / A`` relative to stage 0,
    so the object's volume is ``V_i - F(u_i)``. To keep the water line right for
    preprocessing, the stage positions become ``s_i + F(u_i) / A`` and the readings drop by
    ``F(u_i)`` (in reading units).
    """
    area = float(area or raw.header.tank_cross_section_mm2 or 0.0)
    if not area > 0:
        raise ValueError("fixture subtraction needs the tank cross-section")
    if raw.header.quantity != fixture.header.quantity:
        raise ValueError(f"the fixture recording measures {fixture.header.quantity}, the scan {raw.header.quantity}")
    _check_fixture_tank(raw, fixture)
    scale, _ = _level_scale(raw.header, area)
    curves = []
    for f in fixture.orientations:
        s, v = submerged_volume(f, scale, n_baseline)
        curves.append(((f.tilt_deg or 0.0, f.spin_deg or 0.0), s + v / area, v))
    out = RawScan(header=replace(raw.header, metadata={**raw.header.metadata, "fixture_subtracted": True}),
                  path=raw.path)
    for o in raw.orientations:
        tilt, spin = (o.tilt_deg or 0.0, o.spin_deg or 0.0)
        _, uf, vf = min(curves, key=lambda c: (abs(c[0][0] - tilt), abs(c[0][1] - spin)))
        s, v = submerged_volume(o, scale, n_baseline)
        f_i = np.interp(s + v / area, uf, vf)
        out.orientations.append(replace(o, stage_mm=o.stage_mm + f_i / area, values=o.values - f_i / scale,
                                        flags=[list(x) for x in o.flags]))
    return out


#: A fixture recording whose tank section differs from the scan's by more than this (relative) is refused.
FIXTURE_SECTION_TOL = 0.01


def _check_fixture_tank(scan: RawScan, fixture: RawScan) -> None:
    """Raise ``ValueError`` when the fixture recording states another tank section than the scan (mm^2; both
    stated): its level rises are turned into volumes with the scan's section, so a fixture recorded in another tank
    took off a volume scaled by the sections' ratio, without a word. A configured ``cross_section_mm2`` sets both."""
    mine, theirs = scan.header.tank_cross_section_mm2, fixture.header.tank_cross_section_mm2
    if mine and theirs and abs(theirs / mine - 1.0) > FIXTURE_SECTION_TOL:
        name = f" {fixture.path}" if fixture.path is not None else ""
        raise ValueError(f"the fixture recording{name} states a tank section of {theirs:g} mm^2, the scan "
                         f"{mine:g} mm^2: record the fixture in the scan's tank (its level rises are read with the "
                         "scan's section), or, when both are the same tank, set source.reader.cross_section_mm2")


def _dip_place(o: OrientationScan) -> str:
    """Where dip ``o`` is in its file, for messages: its rig angles (deg) and, for the authors' CSV, its rows
    (``SN``)."""
    rows = o.meta.get("rows") if isinstance(o.meta, dict) else None
    where = f", SN {rows[0]}-{rows[1]}" if rows and rows[0] != rows[1] else f", SN {rows[0]}" if rows else ""
    angles = f"tilt {o.tilt_deg:g}, spin {o.spin_deg:g} deg" if o.tilt_deg is not None and o.spin_deg is not None \
        else ""
    inner = ", ".join(x for x in (angles, where.lstrip(", ")) if x)
    return f" ({inner})" if inner else ""


def _span(values: np.ndarray) -> str:
    """The readings' range, in reading units, for messages."""
    return f"all {values[0]:g}" if np.ptp(values) == 0 else f"{values.min():g} to {values.max():g}"


def profile_centroids(raw: RawScan, area: float) -> np.ndarray:
    """Per orientation, the volume-weighted mean water line ``u`` (mm, relative to stage 0)."""
    out = []
    for o in raw.orientations:
        scale, _ = _level_scale(raw.header, area)
        s, v = submerged_volume(o, scale)
        u = s + v / area
        dv = np.diff(v)
        if dv.sum() <= 0:
            raise ValueError(f"orientation {o.k}{_dip_place(o)}: the reading never rises ({len(o.values)} reading(s), "
                             f"{_span(o.values)}): the object never reached the water, or its rows are a stray one; "
                             "remove the dip's rows or check the sensor")
        out.append(float(np.sum(0.5 * (u[1:] + u[:-1]) * dv) / dv.sum()))
    return np.asarray(out)


def geometry_start_heights(raw: RawScan, area: float, geometry: RigGeometry, use: list[int] | None = None,
                           centre: str = "extent") -> tuple[np.ndarray, dict]:
    """Per-orientation water line at stage 0 from the rig geometry, for recordings that do not
    know the start height ``t0`` (the authors' CSV): ``t_start_k = t0 + geometry.height_shift(tilt_k)``.

    ``t0`` places the object frame's origin on the spin axis: ``centre="extent"`` midway between
    first contact and full submersion of the least tilted dips in ``use`` (which centres the
    object in the grid), ``"centroid"`` at their mean profile centroid.

    Returns:
        ``(t_start (K,), info)``; ``info`` holds ``t0_mm``, the geometry, the dip centroids'
        heights ``h_k`` in the object frame (mm) and ``centroid_rms_mm``: the RMS of ``h_k -
        c . theta_k`` after fitting one centroid ``c`` to the dips in ``use``: a rigid object has
        one centroid, so this is how far the geometry is from explaining the dips' positions.
    """
    tilt = np.array([o.tilt_deg or 0.0 for o in raw.orientations])
    spin = np.array([o.spin_deg or 0.0 for o in raw.orientations])
    cent = profile_centroids(raw, area)
    idx = np.arange(len(cent)) if use is None else np.asarray(sorted(use), dtype=int)
    if idx.size < 1:
        raise ValueError("no orientation to place the start heights with")
    shift = geometry.height_shift(tilt)
    low = idx[np.isclose(tilt[idx], tilt[idx].min())]
    if centre == "extent":
        scale, _ = _level_scale(raw.header, area)
        mids = []
        for k in low:
            s, v = submerged_volume(raw.orientations[k], scale)
            u = s + v / area
            mids.append(0.5 * (np.interp(0.01 * v[-1], v, u) + np.interp(0.99 * v[-1], v, u)))
        t0 = -float(np.mean(np.asarray(mids) + shift[low]))
    elif centre == "centroid":
        t0 = -float(np.mean(cent[low] + shift[low]))
    else:
        raise ValueError(f"centre must be 'centroid' or 'extent', got {centre!r}")
    t_start = t0 + shift
    heights = t_start + cent
    dirs = geometry.directions(tilt, spin).numpy()
    c, *_ = np.linalg.lstsq(dirs[idx], heights[idx], rcond=None)
    residual = heights[idx] - dirs[idx] @ c
    info = {"t0_mm": t0, "geometry": geometry.to_dict(), "centre": centre, "centroid_mm": [float(x) for x in c],
            "centroid_rms_mm": float(np.sqrt(np.mean(residual**2))), "used_orientations": [int(i) for i in idx],
            "centroid_heights_mm": [float(h) for h in heights]}
    return t_start, info


# ============================================================================ orientations
def interpolate_orientations(measurement: DipMeasurement, targets, k: int = 3, max_angle_deg: float = 10.0,
                             tol_deg: float = 0.5) -> DipMeasurement:
    """Add profiles for ``targets`` ``(T, 3)`` interpolated from the ``k`` nearest measured
    directions (weights inversely proportional to the angle), for targets within
    ``max_angle_deg`` of a measured direction and not closer than ``tol_deg`` to one.

    The measured profiles are kept as they are; the result has them first.
    """
    m = measurement
    d = m.directions.numpy() / np.linalg.norm(m.directions.numpy(), axis=1, keepdims=True)
    t = np.asarray(torch.as_tensor(targets, dtype=torch.float64).numpy())
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(t @ d.T, -1.0, 1.0)))  # (T, K)
    nearest = angles.min(axis=1)
    use = (nearest <= max_angle_deg) & (nearest > tol_deg)
    if not use.any():
        return m
    ang = angles[use]
    idx = np.argsort(ang, axis=1)[:, :k]
    w = 1.0 / np.take_along_axis(ang, idx, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    new = np.einsum("tk,tkm->tm", w, m.profiles.numpy()[idx])
    dirs = np.concatenate([d, t[use]])
    prof = np.concatenate([m.profiles.numpy(), new])
    sigma = None
    if m.sigma is not None:
        sigma = np.concatenate([m.sigma.numpy(), np.einsum("tk,tkm->tm", w, m.sigma.numpy()[idx])])
    return DipMeasurement(dirs, prof, m.slab_thickness, np.full(len(dirs), m.offsets[0].item()), sigma,
                          {**m.metadata, "interpolated_orientations": int(use.sum())})


# ============================================================================ the reader
def check_reader_options(tail_fraction: float = 0.1, tail_tol: float = 0.04, interpolate: dict | None = None,
                         fixture: str | Path | None = None, geometry=None) -> None:
    """Raise ``ValueError`` naming the reader's option (``source.reader.*``) for a value no recording can use, before
    the file is read: ``tail_fraction`` not a fraction in (0, 1] (0 and -1 looked at the last 2 readings, 2 an
    ``IndexError``), ``tail_tol`` not a fraction in (0, 1) (NaN, inf or 2 kept every still-rising dip as complete,
    0 flagged every dip), an ``interpolate`` that is not ``{n, k, max_angle_deg, tol_deg}`` with a count ``n`` and
    ``k`` >= 1 and angles (deg) in range (``max_angle_deg=-1`` or NaN added no direction, without a word), a
    ``fixture`` that is no file, a ``geometry`` that is no mapping of the rig's values."""
    if not is_real(tail_fraction) or not 0 < tail_fraction <= 1:  # NaN fails too
        raise ValueError(f"tail_fraction (source.reader.tail_fraction) must be a fraction in (0, 1] (the share of a "
                         f"dip's last readings that tells a truncated dip; default 0.1), got {tail_fraction!r}")
    if not is_real(tail_tol) or not 0 < tail_tol < 1:
        raise ValueError(f"tail_tol (source.reader.tail_tol) must be a fraction in (0, 1) (the share of a dip's total "
                         f"rise its tail may still rise; default 0.04), got {tail_tol!r}")
    if interpolate is not None and not isinstance(interpolate, Mapping):
        raise ValueError(f"interpolate (source.reader.interpolate) must be null or {{n, k, max_angle_deg, tol_deg}}, "
                         f"got {interpolate!r}")
    if interpolate:
        unknown = sorted(str(key) for key in interpolate if key not in ("n", "k", "max_angle_deg", "tol_deg"))
        if unknown or "n" not in interpolate:
            raise ValueError(f"interpolate (source.reader.interpolate) takes n (the Fibonacci targets, required), k, "
                             f"max_angle_deg and tol_deg, got {dict(interpolate)!r}")
        whole_number("source.reader.interpolate.n", interpolate["n"], 1)
        whole_number("source.reader.interpolate.k", interpolate.get("k", 3), 1)
        for key, default, zero in (("max_angle_deg", 10.0, False), ("tol_deg", 0.5, True)):
            value = interpolate.get(key, default)
            if not is_real(value) or not (0 <= value if zero else 0 < value) or not value <= 180:  # NaN fails too
                raise ValueError(f"source.reader.interpolate.{key} must be an angle (deg) in {'[' if zero else '('}0, "
                                 f"180], got {value!r}")
    if fixture is not None and (not isinstance(fixture, (str, Path)) or not Path(fixture).is_file()):
        found = "a folder" if isinstance(fixture, (str, Path)) and Path(fixture).is_dir() else "no file"
        raise ValueError(f"fixture (source.reader.fixture) must be a fixture-only recording's file (.jsonl, .csv) or "
                         f"null, got {fixture!r} ({found})")
    if geometry is not None and not isinstance(geometry, (RigGeometry, Mapping)):
        raise ValueError(f"geometry (source.reader.geometry) must be a mapping of the rig's values (e.g. "
                         f"{{pivot_mm: 188, tilt_axis_offset_mm: -18}}) or null, got {geometry!r}")


def prepare_recording(path: str | Path, *, cross_section_mm2: float | None = None, fixture: str | Path | None = None,
                      geometry: RigGeometry | dict | None = None, calibration: str | Path | None = None,
                      centre: str = "extent", truncated: str = "drop", tail_fraction: float = 0.1,
                      tail_tol: float = 0.04, max_cross_section: float | None = None, ndim: int | None = None,
                      slab_mm: float | None = None) -> tuple[RawScan, RigGeometry, dict]:
    """A recording made ready for :func:`~dipnet.core.geometry.invert_scan` and preprocessing.

    Reads the file, keeps complete dips (:func:`dipnet.core.rawscan.complete_dips`, with a warning
    for the others), resolves the geometry (``geometry`` values or a ``calibration`` file), repairs outlier readings
    or rejects their dips with its level drift taken out (:func:`~dipnet.preprocessing.preprocess.
    repair_without_drift`, with ``max_cross_section`` mm^2 capping the physical rise per step and ``slab_mm``, the
    slab thickness, bounding the gap flagged readings may leave; reported in
    ``info["readings"]``; the truncated dips are found with that drift taken out too),
    subtracts a fixture recording (in the rig's commanded coordinates with the geometry's
    cross-section), keeps complete dips, drops or keeps truncated ones and, when the recording
    does not know its start height (the authors' CSV), gives every dip ``t_start_mm = t0``
    placed by :func:`geometry_start_heights` (the geometry's height shift is *not* in it:
    ``invert_scan`` adds it). Arguments as for :func:`read_raw_recording`.

    ``ndim``: the grid's dimension, which the recording's must match (checked before its readings are
    repaired: a 3D recording's rises exceed a 2D grid's physical cap, and were "repaired" before the refusal).

    Returns ``(raw scan in the rig's commanded coordinates, geometry, info)``; ``info["calibration"]`` names the
    calibration file (path, rig, tank, method, created) when the geometry is one's.
    """
    check_reader_options(tail_fraction, tail_tol, fixture=fixture, geometry=geometry)
    raw = read_scan(path)
    # the section the file states (the authors' CSV states none: its default is the authors' tank)
    stated = None if Path(path).suffix.lower() == ".csv" else raw.header.tank_cross_section_mm2
    if cross_section_mm2 is not None:
        raw.header = replace(raw.header, tank_cross_section_mm2=float(cross_section_mm2))
    if ndim is not None and raw.header.ndim != ndim:
        raise ValueError(f"{path}: a {raw.header.ndim}D recording (its header's ndim) for a {ndim}D grid: "
                         f"set ndim={raw.header.ndim}")
    incomplete = [o.k for o in raw.orientations if not o.complete]
    raw.orientations = complete_dips(raw)
    if calibration is not None and as_geometry(geometry) != RigGeometry():
        raise ValueError("give the rig geometry either as a calibration file or as values, not both")
    if calibration is not None and raw.header.ndim == 2:  # calibrate.py and calibration=self refuse 2D scans
        raise ValueError(f"{path}: a 2D recording (its header's ndim) read with the rig calibration file {calibration} "
                         "(source.reader.calibration): a calibration file holds a 3D rig's geometry (its tilt and "
                         "spin axes, its section in mm^2), which a 2D recording's dips (angles in a plane, its tank a "
                         "width in mm) cannot take; leave source.reader.calibration unset for a 2D recording")
    calibrated = None if calibration is None else scan_calibration(calibration, raw.header)
    if calibrated is not None:
        geometry = calibrated.geometry
        if cross_section_mm2 is not None:
            geometry = geometry.with_values(cross_section_mm2=float(cross_section_mm2))
    geometry = as_geometry(geometry)
    rotary = {name: getattr(geometry, name) for name in ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg",
                                                          "spin_zero_deg") if getattr(geometry, name)}
    if rotary and raw.header.ndim == 2:  # invert_scan: "orientation 0 has no rig angles", naming no option
        given = ", ".join(f"source.reader.geometry.{name}={value:g}" for name, value in rotary.items())
        raise ValueError(f"{path}: a 2D recording (its header's ndim) has no tilt and spin axes for the rig geometry "
                         f"given ({given}) to move: leave them 0 for a 2D recording (its step_scale, "
                         "cross_section_mm2, level_drift_mm_per_s and sensor_lag_s apply)")
    # with the level drift taken out: a drift over a dip's rest readings passes for outliers
    raw, readings = repair_without_drift(raw, geometry.level_drift_mm_per_s, max_cross_section=max_cross_section,
                                         slab_mm=slab_mm)
    if calibration is None and geometry.is_ideal:
        _warn_recorded_geometry_unused(raw, path)
    area = geometry.area(raw.header.tank_cross_section_mm2 or 0.0)
    if not area > 0:
        raise ValueError(f"{path}: the tank cross-section is unknown: set cross_section_mm2")
    if fixture is not None:
        raw = subtract_fixture(raw, read_scan(fixture, cross_section_mm2), area)
    cut = truncated_orientations(level_drift_removed(raw, geometry.level_drift_mm_per_s), tail_fraction, tail_tol)
    configured = cross_section_mm2 if cross_section_mm2 is not None else \
        (geometry.cross_section_mm2 if calibrated is None else None)
    info: dict = {"truncated": cut, "truncated_policy": truncated, "geometry": geometry.to_dict(),
                  "readings": readings.to_json(), "incomplete": incomplete,
                  "cross_section_mm2": {"used": area, "recorded": stated, "configured": configured}}
    if calibrated is not None:  # which file placed the dips: the validation names it when they do not fit
        info["calibration"] = {"path": str(calibration), "rig": calibrated.rig, "tank": calibrated.tank,
                               "method": calibrated.method, "created": calibrated.created}
    if truncated == "drop":
        if len(cut) == len(raw.orientations):
            raise ValueError(f"{path}: every dip is truncated; use truncated='keep'")
        if cut:
            _warn_dropped(path, cut, len(raw.orientations))
        raw.orientations = [o for o in raw.orientations if o.k not in cut]
    elif truncated != "keep":
        raise ValueError(f"truncated must be 'drop' or 'keep', got {truncated!r}")
    if any(o.meta.get("t_start_mm", raw.header.t_start_mm) is None for o in raw.orientations):
        complete = [i for i, o in enumerate(raw.orientations) if o.k not in cut]
        _, placed = geometry_start_heights(invert_scan(raw, geometry), area, geometry, complete, centre)
        for o in raw.orientations:
            o.meta = {**o.meta, "t_start_mm": placed["t0_mm"]}
        info["start_heights"] = placed
    return raw, geometry, info


def _warn_recorded_geometry_unused(raw: RawScan, path: str | Path) -> None:
    """Warn when ``raw`` was scanned with a rig geometry that is not ideal (``scan.py +rig.calibration=FILE`` or
    ``rig.geometry``, recorded in its header) and is read on the ideal rig because the reader was given none:
    the recorded start heights' pivot and offset shift is then undone, and the tilt and spin zeros, the step
    scale, drift and lag are ignored (a torus scanned on a rig with step scale 1.03 and tilt zero 2 deg, with
    its reference calibration: IoU 0.82 instead of 0.94, ``consistent``, no word)."""
    recorded = scan_geometry(raw.header)
    if recorded.is_ideal:
        return
    scan_config = raw.header.config.get("scan")
    rig = scan_config.get("rig") if isinstance(scan_config, dict) else None
    file = rig.get("calibration") if isinstance(rig, dict) else None
    ideal = RigGeometry()
    differ = ", ".join(f"{name}={value:.6g}" for name, value in recorded.to_dict().items()
                       if name != "cross_section_mm2" and value != getattr(ideal, name))
    remedy = (f"give the reader that calibration: calibration={file} (reconstruct.py: "
              f"source.reader.calibration={file})") if file else \
        "give the reader that geometry (reconstruct.py: source.reader.geometry={...}) or its calibration file"
    message = (f"{path} was scanned with a rig geometry ({differ}; recorded in its header) and is read on the ideal "
               f"rig, since the reader is given no geometry: the dips' start heights, directions and stage travel are "
               f"then not the rig's; {remedy}")
    log_and_warn(log, message, stacklevel=3)


#: Dropping more than this share of the dips as truncated is refused: the rest cannot stand for the scan (the
#: authors' recording loses 16 of its 32 dips, those tilted 20-35 deg, and still reconstructs; in the audit 14 of
#: 16 dips ended early).
MAX_DROPPED_SHARE = 0.75


def _warn_dropped(path: str | Path, cut: list[int], total: int) -> None:
    """Warn that the truncated dips ``cut`` (of ``total``) are dropped; refuse when most of them are."""
    listed = ", ".join(str(k) for k in cut[:8]) + (", ..." if len(cut) > 8 else "")
    found = f"{path}: {len(cut)} of {total} dips end before the object is under water (dips {listed})"
    remedy = "source.reader.truncated=keep uses them as truncated dips; a deeper protocol.stop_mm records them whole"
    if len(cut) > MAX_DROPPED_SHARE * total:
        raise ValueError(f"{found}: dropping more than {MAX_DROPPED_SHARE:.0%} of the dips leaves too few to stand "
                         f"for the scan ({remedy})")
    message = f"{found}: dropped ({remedy})"
    log_and_warn(log, message, stacklevel=3)


def finish_measurement(measurement: DipMeasurement, symmetry: dict | None = None,
                       interpolate: dict | None = None) -> DipMeasurement:
    """The readers' last steps: symmetry expansion (``{n_fold, mirror, mirror_azimuth_deg, tol_deg}``,
    :func:`dipnet.preprocessing.symmetry.apply_symmetry`) and interpolation (``{n, k, max_angle_deg}``:
    Fibonacci-hemisphere targets for :func:`interpolate_orientations`)."""
    m = measurement
    m = apply_symmetry(m, symmetry)
    if interpolate:
        opts = dict(interpolate)
        m = interpolate_orientations(m, fibonacci_hemisphere(int(opts.pop("n"))), **opts)
    return m


@forwards_to(prepare_recording)
def read_raw_recording(path: str | Path, grid: Grid, n_slabs: int | None = None, *,
                       t_start: str | float = "geometry", smooth: bool = False, symmetry: dict | None = None,
                       interpolate: dict | None = None, **options) -> DipMeasurement:
    """A recorded scan (dipnet ``.jsonl`` or the authors' ``.csv``) as a measurement on ``grid``.

    Args:
        path: the recording.
        grid, n_slabs: the reconstruction grid and slab count (default ``grid.n``).
        t_start: ``"geometry"``: the recording's start heights moved by the geometry
            (:func:`~dipnet.core.geometry.invert_scan`), placed by :func:`geometry_start_heights`
            with ``centre`` when the recording has none; or any ``t_start`` of
            :func:`dipnet.preprocessing.preprocess.preprocess`.
        smooth: the paper's 5-tap Gaussian. Off by default, as for simulated sources: the operator
            does not blur, so smoothing noise-free profiles blurs the reconstruction (an ideal ball
            at 24^3 lost 9% of its volume to the threshold); turn it on for noisy recordings.
        symmetry, interpolate: see :func:`finish_measurement`.
        options: for :func:`prepare_recording`:

            * ``cross_section_mm2``: tank free cross-section (default: the file's; the authors'
              CSV: 183,600);
            * ``fixture``: a fixture-only recording to subtract (:func:`subtract_fixture`);
            * ``geometry``: the rig geometry (:class:`~dipnet.core.geometry.RigGeometry` or its
              fields, e.g. ``{pivot_mm: 188, tilt_axis_offset_mm: -18}``); default the ideal rig;
            * ``calibration``: a rig calibration file instead of ``geometry``, for a 3D recording (a 2D one is refused)
              (:func:`~dipnet.core.calibration_file.scan_calibration`: it must be the
              recording's rig and tank); its cross-section wins unless ``cross_section_mm2`` is given;
            * ``centre``: see :func:`geometry_start_heights`;
            * ``truncated``: ``"drop"`` or ``"keep"`` dips that were still rising when the scan
              stopped (:func:`truncated_orientations` with ``tail_fraction``, ``tail_tol``);
              kept ones are continued flat, which puts no volume beyond the scanned range.

    Returns:
        The measurement, ``metadata["recorded"]`` holding what was done (geometry, start heights,
        dropped dips, counts, the tank section used and the one the file states).
    """
    check_reader_options(interpolate=interpolate)  # before the recording is read and prepared
    raw, geometry, info = prepare_recording(path, max_cross_section=max_object_section(grid), ndim=grid.ndim,
                                            slab_mm=grid.extent / (n_slabs or grid.n), **options)
    # cleaned once, by prepare_recording: complete dips kept, outliers repaired
    m = preprocess(invert_scan(raw, geometry), grid=grid, n_slabs=n_slabs,
                   t_start="metadata" if t_start == "geometry" else t_start, smooth=smooth, repair=False,
                   include_incomplete=True)
    info["measured_orientations"] = m.n_orientations
    m = finish_measurement(m, symmetry, interpolate)
    m.metadata = {**m.metadata, "recorded": info, "path": str(path), "readings": info["readings"]}
    return m
