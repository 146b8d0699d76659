"""DipMeasurement: what solvers consume, and its file format.

File format (version 1): one ``.npz`` holding the arrays ``directions`` ``(K, d)``,
``profiles`` ``(K, M)`` (slab volumes, mm^3; mm^2 in 2D), ``offsets`` ``(K,)`` (mm, the
height ``t`` of the lower edge of slab 0 in the object frame), optional ``sigma``
(``(K, M)``, mm^3, noise standard deviation per slab) and ``metadata`` (a JSON string with
``format``, ``version``, ``slab_thickness`` in mm and free-form provenance).
"""

from __future__ import annotations

import json
import logging
import math
import os
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.warn import log_and_warn

log = logging.getLogger(__name__)

FORMAT_NAME = "dipnet.measurement"
FORMAT_VERSION = 1
_MAD = 1.4826  # MAD -> standard deviation for Gaussian data
#: A share of a dip's volume beyond the reconstruction's slabs above this is named: the object does not fit the grid.
BEYOND_SLABS_TOL = 0.01
#: How far the object reaches (:meth:`DipMeasurement.reach`) counts only volume above this many noise sigmas.
REACH_SIGMAS = 5.0
#: A slab holding at most this share of its profile's largest volume is empty (:func:`filled_slabs`).
FILLED_REL_TOL = 0.005


class MeasurementFileError(ValueError):
    """A measurement file is missing, unreadable or inconsistent."""


def _float64(values, name: str) -> torch.Tensor:
    """``values`` (a tensor, a numpy array, a list) as a float64 tensor; a numpy view with negative strides
    (``np.flip``, ``[::-1]``) is copied, as torch takes none. Complex values raise :class:`MeasurementFileError`
    naming the array ``name`` (the cast dropped their imaginary parts with only torch's warning)."""
    if values.is_complex() if isinstance(values, torch.Tensor) else np.iscomplexobj(values):
        dtype = str(getattr(values, "dtype", "complex")).removeprefix("torch.")
        raise MeasurementFileError(f"measurement array {name!r} holds complex numbers ({dtype}): a measurement's "
                                   "arrays are real (slab volumes in mm^3, directions, offsets in mm); give the real "
                                   "part where it was made, if that is what it means")
    if isinstance(values, np.ndarray):
        values = np.ascontiguousarray(values)
    return torch.as_tensor(values, dtype=torch.float64)


def _thickness(value) -> float:
    """``slab_thickness`` (a number, or a tensor or array holding one) as a float in mm; anything else (a string,
    one value per dip) raises :class:`MeasurementFileError`: every slab of a measurement has the same thickness."""
    message = f"slab_thickness must be one number of mm (the same for every slab and dip), got {value!r}"
    if isinstance(value, (str, bytes, bool)):
        raise MeasurementFileError(message)
    try:
        array = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeasurementFileError(message) from exc
    if array.size != 1:
        raise MeasurementFileError(message)
    return float(array.reshape(()))


def filled_slabs(target: torch.Tensor, rel_tol: float = FILLED_REL_TOL) -> torch.Tensor:
    """Boolean ``(K, M)``: the slabs of each profile ``target`` (``(K, M)``, mm^3) holding more than
    ``rel_tol`` x the profile's largest volume."""
    return target > rel_tol * target.abs().amax(dim=-1, keepdim=True)


#: Provenance entries a job reads after the solve, by their form: a hand-edited ``.npz`` holding another form ended
#: in a traceback there, the result lost (mappings; lists of a number or ``None`` per dip; lists of a pair per dip;
#: numbers or ``None``).
PROVENANCE_MAPPINGS = ("recorded", "readings", "symmetry_fit")
PROVENANCE_PER_DIP = ("outside_share", "outside_mm", "tail_slope", "readings_per_dip")
PROVENANCE_PAIRS = ("reach_mm", "level_drop")
PROVENANCE_NUMBERS = ("reading_noise_volume", "reading_noise_ratio", "reading_noise_leak", "reading_quantum",
                      "reading_quantum_volume")


def check_provenance(provenance: dict) -> None:
    """Raise :class:`MeasurementFileError` naming the first entry of ``provenance`` not of the form the job reads
    (:data:`PROVENANCE_MAPPINGS`, :data:`PROVENANCE_PER_DIP`, :data:`PROVENANCE_PAIRS`, :data:`PROVENANCE_NUMBERS`);
    a missing or ``null`` entry is not known, and fine."""
    def number(v) -> bool:
        return v is None or is_real(v)

    def pairs(v) -> bool:
        return isinstance(v, list) and all(isinstance(r, list) and len(r) == 2 and all(map(number, r)) for r in v)

    forms = [(PROVENANCE_MAPPINGS, lambda v: isinstance(v, dict), "a JSON object"),
             (PROVENANCE_PER_DIP, lambda v: isinstance(v, list) and all(map(number, v)),
              "a list with a number per dip"),
             (PROVENANCE_PAIRS, pairs, "a list with a [number, number] pair per dip"),
             (PROVENANCE_NUMBERS, is_real, "a number")]
    for keys, fits, form in forms:
        for key in keys:
            value = provenance.get(key)
            if value is not None and not fits(value):
                raise MeasurementFileError(f"metadata provenance {key!r} must be {form} or null, got "
                                           f"{json.dumps(value)[:60]}: a hand-edited file?")


def _per_dip(values, k: int, default: float) -> np.ndarray:
    """A per-dip metadata list as ``(k,)`` float64: itself when it has ``k`` entries (``None`` read as NaN), else
    its largest finite entry for every dip (the list of the measured dips of a measurement with symmetry images
    or interpolated directions), else ``default``."""
    array = np.asarray([np.nan if v is None else v for v in (values or [])], dtype=np.float64).reshape(-1)
    if array.size == k:
        return array
    finite = array[np.isfinite(array)]
    return np.full(k, float(finite.max()) if finite.size else default)


_HIGHPASS_GAIN = math.sqrt(3.0 / 8.0)  # rms of (1 - [1, 2, 1] / 4) applied to white noise


def estimate_slab_sigma(profiles: torch.Tensor) -> float:
    """A per-slab noise sigma (mm^3) estimated from the profiles ``(K, M)`` themselves: the
    high-pass residual ``g - [1, 2, 1] / 4 * g`` along the slabs, robust sigma (MAD) divided
    by the filter's white-noise gain. Smooth signal leaks a little into it (more noise, fewer
    warnings); smoothing in preprocessing hides some noise from it. The spread of the
    profiles' totals is not used: on real rigs it is dominated by systematic errors
    (truncated dips, drift), which are exactly what the consistency check
    (:mod:`dipnet.evaluation.consistency`, which uses this estimate) should expose.

    Profiles of fewer than 3 slabs have no high-pass residual: the robust spread (MAD) of their slab volumes is
    returned instead, an upper bound that holds their signal too (it was NaN, which silently skipped the
    consistency check's residual limit).
    """
    p = profiles.double().numpy()
    if p.shape[-1] < 3:
        return _MAD * float(np.median(np.abs(p - np.median(p))))
    high = p[:, 1:-1] - 0.25 * (p[:, :-2] + 2 * p[:, 1:-1] + p[:, 2:])
    return _MAD * float(np.median(np.abs(high - np.median(high)))) / _HIGHPASS_GAIN


def reading_slab_sigma(metadata: dict) -> float | None:
    """The per-slab noise sigma (mm^3) that the readings' own scatter gives: ``sqrt(2)`` times the noise of one reading
    (preprocessing's ``metadata["reading_noise_volume"]``), a slab being the difference of two cumulative readings;
    ``None`` when the readings' noise was not recorded."""
    reading = metadata.get("reading_noise_volume")
    return None if reading is None else math.sqrt(2.0) * float(reading)


def robust_volume(profiles: torch.Tensor) -> tuple[float, float]:
    """``(volume, spread)``: a robust mean of the profiles' totals (the mean of those within
    3 MAD-sigmas of the median) and its standard error (robust sigma / sqrt(K)), mm^3.

    Args:
        profiles: slab volumes ``(K, M)``, mm^3.
    """
    totals = profiles.sum(1).double().numpy()
    median = float(np.median(totals))
    sigma = _MAD * float(np.median(np.abs(totals - median)))
    keep = np.abs(totals - median) <= 3 * sigma if sigma > 0 else np.ones_like(totals, dtype=bool)
    return float(totals[keep].mean()), sigma / math.sqrt(int(keep.sum()))


def _json_ready(value, where: str):
    """``value`` (metadata) with numpy and torch numbers and arrays as Python numbers and lists, and paths as strings,
    for :func:`json.dumps`; any other value JSON cannot store raises :class:`MeasurementFileError` naming ``where``
    (its key path, e.g. ``metadata['shape']``)."""
    if isinstance(value, dict):
        return {key: _json_ready(item, f"{where}[{key!r}]") for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(item, f"{where}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, (np.ndarray, np.generic)):
        return _json_ready(value.tolist(), where)  # complex or object entries are refused below
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if value is None or isinstance(value, (str, int, float)):
        return value
    raise MeasurementFileError(f"{where} holds a {type(value).__name__} ({value!r:.60}), which the file's JSON cannot "
                               "store: give it as a number, string, list or dict")


@dataclass
class DipMeasurement:
    """Uniform slab volumes per orientation.

    Attributes:
        directions: unit "up" vectors in the object frame, ``(K, d)`` float64 (rows of other lengths are scaled to
            unit length, as the operators do: the fitted heights and the placement checks read them as unit).
        profiles: slab volumes in mm^3 (mm^2 in 2D), ``(K, M)`` float64, ordered by height.
        slab_thickness: slab thickness in mm.
        offsets: height ``t`` (mm) of the lower edge of slab 0 per orientation, ``(K,)``.
        sigma: optional noise standard deviation per slab (mm^3), ``(K, M)``.
        metadata: provenance (source, shape, noise settings, ...), a dict, JSON-serialisable (numpy and torch
            values are written as numbers and lists by :meth:`save`; ``None`` is an empty dict).
    """

    directions: torch.Tensor
    profiles: torch.Tensor
    slab_thickness: float
    offsets: torch.Tensor
    sigma: torch.Tensor | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.directions = _float64(self.directions, "directions")
        self.profiles = _float64(self.profiles, "profiles")
        self.offsets = _float64(self.offsets, "offsets").reshape(-1)
        self.slab_thickness = _thickness(self.slab_thickness)
        if self.metadata is None:
            self.metadata = {}
        if not isinstance(self.metadata, dict):
            raise MeasurementFileError(f"metadata must be a dict (provenance, JSON-serialisable), got "
                                       f"{type(self.metadata).__name__}")
        if self.sigma is not None:
            self.sigma = _float64(self.sigma, "sigma")
            if self.sigma.numel() == 1:
                self.sigma = self.sigma.reshape(1, 1).expand_as(self.profiles).clone()
        self.validate()
        norms = self.directions.norm(dim=1, keepdim=True)
        if not bool(((norms - 1.0).abs() <= 1e-12).all()):  # as the operators do: only the line counts, not its length
            self.directions = self.directions / norms

    @property
    def n_orientations(self) -> int:
        return int(self.profiles.shape[0])

    @property
    def n_slabs(self) -> int:
        return int(self.profiles.shape[1])

    @property
    def ndim(self) -> int:
        return int(self.directions.shape[1])

    def validate(self) -> None:
        """Raise :class:`MeasurementFileError` naming the first inconsistency."""
        d, p, o = self.directions, self.profiles, self.offsets
        if d.ndim != 2 or d.shape[1] not in (2, 3):
            raise MeasurementFileError(f"directions must have shape (K, 2) or (K, 3), got {tuple(d.shape)}")
        if d.shape[0] < 1:
            raise MeasurementFileError("a measurement needs at least 1 dip (orientation), got 0")
        if p.ndim != 2 or p.shape[0] != d.shape[0]:
            raise MeasurementFileError(
                f"profiles must have shape (K, M) with K = {d.shape[0]} orientations, got {tuple(p.shape)}")
        if p.shape[1] < 2:
            raise MeasurementFileError(f"profiles need at least 2 slabs, got {p.shape[1]}")
        if o.shape[0] != d.shape[0]:
            raise MeasurementFileError(f"offsets must have shape ({d.shape[0]},), got {tuple(o.shape)}")
        if not np.isfinite(self.slab_thickness) or self.slab_thickness <= 0:
            raise MeasurementFileError(f"slab_thickness must be a positive number of mm, got {self.slab_thickness}")
        if self.sigma is not None and self.sigma.shape != p.shape:
            raise MeasurementFileError(f"sigma must have the profiles' shape {tuple(p.shape)}")
        arrays = {"profiles": p, "directions": d, "offsets": o, "sigma": self.sigma}
        for name, values in arrays.items():
            bad = 0 if values is None else int((~torch.isfinite(values)).sum())
            if bad:
                raise MeasurementFileError(f"measurement array {name!r} holds {bad} NaN or infinite value(s) "
                                           f"of {values.numel()}")
        if (d.norm(dim=1) < 1e-9).any():
            raise MeasurementFileError("directions contain a zero vector")
        if self.sigma is not None and (self.sigma < 0).any():
            raise MeasurementFileError(f"measurement array 'sigma' holds {int((self.sigma < 0).sum())} negative "
                                       "value(s): noise standard deviations are >= 0")

    def slab_centres(self) -> torch.Tensor:
        """Each slab's centre height along its dip's direction, ``(K, M)`` float64, mm from the frame's origin."""
        steps = (torch.arange(self.n_slabs, dtype=torch.float64) + 0.5) * self.slab_thickness
        return self.offsets.double()[:, None] + steps[None, :]

    def reach(self) -> np.ndarray:
        """How far the object certainly reaches along each dip: ``(K', 2)`` float64 heights ``[low, high]`` (mm,
        the object frame, whose origin is the grid's centre) with some of its volume below ``low`` and some
        above ``high``, beyond noise; a row of NaN for a dip that shows no volume.

        From the readings when preprocessing recorded them (``metadata["reach_mm"]``, one row per dip read:
        ``K'`` may be fewer than the profiles when symmetry images or interpolated directions were added, whose
        reach is a measured dip's or within theirs; :func:`dipnet.preprocessing.preprocess.preprocess`).
        Else from the slabs: a dip's first and last slab holding more than :data:`FILLED_REL_TOL` of its largest
        and :data:`REACH_SIGMAS` noise sigmas (its ``sigma``, and at least ``sqrt(2)`` times the readings' own
        noise, ``metadata["reading_noise_volume"]``, when recorded; without either, :func:`estimate_slab_sigma`)
        put ``low`` at the first one's upper edge and
        ``high`` at the last one's lower edge, each moved two slabs inward when the profiles were smoothed (the
        5-tap filter spreads a slab's volume two slabs on).
        """
        recorded = self.metadata.get("reach_mm")
        if recorded:
            return np.asarray([[np.nan if v is None else v for v in row] for row in recorded], dtype=np.float64)
        p = self.profiles
        reading = reading_slab_sigma(self.metadata)
        if self.sigma is None and reading is None:
            noise = torch.full_like(p, estimate_slab_sigma(p))
        else:
            noise = torch.zeros_like(p) if self.sigma is None else self.sigma.clone()
            noise = noise.clamp(min=0.0 if reading is None else reading)
        full = filled_slabs(p) & (p > REACH_SIGMAS * noise)
        edges = self.offsets[:, None] + self.slab_thickness * torch.arange(self.n_slabs + 1, dtype=torch.float64)
        rows = torch.arange(self.n_orientations)
        first = torch.argmax(full.to(torch.int8), dim=1)
        last = self.n_slabs - 1 - torch.argmax(full.flip(1).to(torch.int8), dim=1)
        spread = 2.0 * self.slab_thickness if self.metadata.get("smoothed") else 0.0
        out = torch.stack([edges[rows, first + 1] + spread, edges[rows, last] - spread], dim=1).numpy()
        out[~full.any(1).numpy()] = np.nan
        return out

    def volume_estimate(self) -> float:
        """Object volume (mm^3): the median over orientations of each profile's sum."""
        return float(self.profiles.sum(1).median())

    def resampled(self, edges: torch.Tensor, rel_tol: float | None = None) -> torch.Tensor:
        """Slab volumes on other slab boundaries ``edges`` ``(M' + 1,)`` (mm, increasing; a tensor or array, the
        same for every orientation), by linear interpolation of the cumulative volume; ``(K, M')``.

        Volume outside ``[edges[0], edges[-1]]`` is lost; with ``rel_tol`` given, a loss above that share
        of a profile's volume is logged and warned about, naming both slab ranges (the grid is too small
        for the object).

        Raises:
            MeasurementFileError: ``edges`` that are not finite and increasing (heights ``t`` grow upward, in the
                order the slabs go under water: decreasing edges would give every slab a negative volume).
        """
        edges = torch.as_tensor(edges, dtype=torch.float64)
        if edges.ndim != 1 or edges.numel() < 2 or not bool(torch.isfinite(edges).all()) \
                or not bool((torch.diff(edges) > 0).all()):
            got = (f"{edges.numel()} edges from {float(edges[0]):g} to {float(edges[-1]):g} mm" if edges.ndim == 1
                   and edges.numel() >= 2 else f"shape {tuple(edges.shape)}")
            raise MeasurementFileError(f"re-binning needs finite, increasing slab edges (mm, heights t growing upward, "
                                       f"at least 1 slab), got {got}")
        k, m = self.profiles.shape
        cum = torch.cat([torch.zeros(k, 1, dtype=torch.float64), torch.cumsum(self.profiles, 1)], 1)
        src = self.offsets[:, None] + self.slab_thickness * torch.arange(m + 1, dtype=torch.float64)
        out = torch.from_numpy(np.diff(np.stack([np.interp(edges.numpy(), src[i].numpy(), cum[i].numpy())
                                                 for i in range(k)]), axis=1))
        total = self.profiles.sum(1)
        lost = float(((total - out.sum(1)).abs() / total.abs().clamp(min=1e-300)).max())
        if rel_tol is not None and lost > rel_tol:
            message = (f"resampling the profiles from slabs [{float(src[:, 0].min()):.1f}, "
                       f"{float(src[:, -1].max()):.1f}]"
                       f" mm onto [{float(edges[0]):.1f}, {float(edges[-1]):.1f}] mm drops up to {100 * lost:.2f}% "
                       "of a profile's volume: the object does not fit the grid (raise extent_mm)")
            log_and_warn(log, message, stacklevel=3)
        return out

    def resampled_sigma(self, edges: torch.Tensor) -> torch.Tensor | None:
        """The noise sigma on other slab boundaries ``edges`` ``(M' + 1,)`` (mm, increasing), ``(K, M')`` mm^3: the
        cumulative variance resampled as :meth:`resampled` does the volumes (independent slabs); ``None`` without
        ``sigma``."""
        if self.sigma is None:
            return None
        return replace(self, profiles=self.sigma.pow(2), sigma=None).resampled(edges).clamp(min=0).sqrt()

    def rebinned(self, edges: torch.Tensor, rel_tol: float = 1e-3) -> "DipMeasurement":
        """This measurement on other uniform slabs ``edges`` ``(M' + 1,)`` (mm, the same for every
        orientation): volumes by :meth:`resampled`, noise sigma by resampling the cumulative
        variance (independent slabs), metadata noting the source slabs.

        Volume outside ``[edges[0], edges[-1]]`` is lost; a loss above ``rel_tol`` of the
        object's volume is logged and warned about (the grid is too small for the object). What the
        metadata says of the slabs is made the new slabs': ``outside_share`` (each dip's share of its volume
        beyond the slabs: what the source slabs held beyond the new ones joins what they left out), and
        ``outside_mm`` (the height the dip's readings span beyond the slabs: the source slabs' width and
        ``outside_mm`` less the new slabs' width); ``reach_mm`` (:meth:`reach`) is set from the source slabs
        when the readings did not record it, so that re-binning does not spread it.
        """
        edges = torch.as_tensor(edges, dtype=torch.float64)
        steps = torch.diff(edges)
        if edges.ndim != 1 or edges.numel() < 3 or not bool((steps > 0).all()):
            raise MeasurementFileError("re-binning needs increasing slab edges (at least 2 slabs)")
        if not torch.allclose(steps, steps.mean().expand_as(steps), rtol=1e-9):
            raise MeasurementFileError("re-binning needs uniform slab edges")
        profiles = self.resampled(edges, rel_tol)
        sigma = self.resampled_sigma(edges)
        metadata = {**self.metadata, "rebinned_from": {"n_slabs": self.n_slabs, "slab_thickness": self.slab_thickness},
                    "reach_mm": [[None if not math.isfinite(v) else float(v) for v in row] for row in self.reach()],
                    **self._beyond_new_slabs(profiles, edges)}
        return DipMeasurement(self.directions, profiles, float(steps[0]), edges[:1].expand(self.n_orientations).clone(),
                              sigma, metadata)

    def _beyond_new_slabs(self, profiles: torch.Tensor, edges: torch.Tensor) -> dict:
        """``outside_share`` and (when the metadata has it) ``outside_mm`` per dip for this measurement re-binned to
        ``profiles`` ``(K, M')`` on ``edges`` ``(M' + 1,)`` mm (see :meth:`rebinned`)."""
        k = self.n_orientations
        before = np.nan_to_num(_per_dip(self.metadata.get("outside_share"), k, 0.0))
        held = profiles.sum(1).numpy() / self.profiles.sum(1).clamp(min=1e-300).numpy()  # of the source's volume
        out = {"outside_share": [float(max(0.0, 1.0 - (1.0 - s) * h)) for s, h in zip(before, held)]}
        if self.metadata.get("outside_mm") is not None:
            spans = np.nan_to_num(_per_dip(self.metadata["outside_mm"], k, 0.0))
            width = self.n_slabs * self.slab_thickness - float(edges[-1] - edges[0])
            out["outside_mm"] = [float(max(0.0, m + width)) for m in spans]
        return out

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write the measurement to ``path`` (``.npz``); returns the path.

        Raises:
            MeasurementFileError: metadata holding a value JSON cannot store (numpy and torch numbers and arrays,
                and paths, are written as numbers, lists and strings), naming its key; nothing is written then.
                A ``path`` that is a folder.
        """
        path = Path(path)
        if path.is_dir():
            raise MeasurementFileError(f"{path} is a folder: give the measurement file's name, e.g. "
                                       f"{path / 'measurement.npz'}")
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
                "slab_thickness": float(self.slab_thickness), **{"provenance": _json_ready(self.metadata, "metadata")}}
        arrays = {"directions": self.directions.numpy(), "profiles": self.profiles.numpy(),
                  "offsets": self.offsets.numpy(), "metadata": np.array(json.dumps(meta))}
        if self.sigma is not None:
            arrays["sigma"] = self.sigma.numpy()
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "DipMeasurement":
        """Read a file written by :meth:`save`; malformed files raise :class:`MeasurementFileError`."""
        path = Path(path)
        if not path.is_file():
            raise MeasurementFileError(f"measurement file not found: {path}")
        try:
            loaded = np.load(path, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):  # a bare .npy array: np.load gives the array itself
                raise MeasurementFileError(f"{path}: a single .npy array ({loaded.shape} {loaded.dtype}), not a .npz "
                                           "measurement file (directions, profiles, offsets, metadata): write it with "
                                           "DipMeasurement.save")
            with loaded as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            if isinstance(exc, MeasurementFileError):
                raise
            raise MeasurementFileError(f"{path}: not a readable .npz measurement file ({exc})") from exc
        missing = {"directions", "profiles", "offsets", "metadata"} - set(arrays)
        if missing:
            raise MeasurementFileError(f"{path}: missing array(s) {sorted(missing)}")
        try:
            meta = json.loads(str(arrays["metadata"]))
        except json.JSONDecodeError as exc:
            raise MeasurementFileError(f"{path}: metadata is not valid JSON ({exc})") from exc
        if not isinstance(meta, dict):  # valid JSON, but a list, string or number: no format to read
            raise MeasurementFileError(f"{path}: metadata must be a JSON object (format, version, slab_thickness, "
                                       f"provenance), got a {type(meta).__name__}: not a dipnet measurement")
        if meta.get("format") != FORMAT_NAME:
            raise MeasurementFileError(f"{path}: not a dipnet measurement (format={meta.get('format')!r})")
        if meta.get("version") != FORMAT_VERSION:
            raise MeasurementFileError(f"{path}: unsupported format version {meta.get('version')!r}")
        try:
            if isinstance(meta.get("provenance"), dict):
                check_provenance(meta["provenance"])
            if "slab_thickness" not in meta:
                raise MeasurementFileError("metadata has no slab_thickness (mm): not a dipnet measurement")
            return cls(directions=torch.from_numpy(arrays["directions"]),
                       profiles=torch.from_numpy(arrays["profiles"]),
                       slab_thickness=meta["slab_thickness"],  # checked as one number (true, "2.5" are refused)
                       offsets=torch.from_numpy(arrays["offsets"]),
                       sigma=torch.from_numpy(arrays["sigma"]) if "sigma" in arrays else None,
                       metadata=meta.get("provenance", {}))
        except MeasurementFileError as exc:
            raise MeasurementFileError(f"{path}: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise MeasurementFileError(f"{path}: malformed measurement ({exc})") from exc
