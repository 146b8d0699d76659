"""Recorded measurement sources (``source=recorded``), and what every source hands the job.

A source has four methods (the simulated one is :class:`dipnet.simulator.source.SimulatedSource`):
``truth`` (the object to score against, or ``None``), ``extent_mm`` (a grid side of its own),
``measure`` (an :class:`Acquisition`: the finished measurement, its checks, its raw scan) and
``record`` (a :class:`Recording`: the raw scan for self-calibration).

:class:`RecordedSource` reads a file, chosen by type (:func:`read_recorded`):

* ``.npz``: a :class:`~dipnet.core.measurement.DipMeasurement` file, re-binned onto the grid's
  ``n_slabs`` slabs (any resolution; :meth:`~dipnet.core.measurement.DipMeasurement.rebinned`);
* ``.jsonl`` (a dipnet raw scan from ``scripts/scan.py``) or ``.csv`` (the authors' robot):
  preprocessed onto the grid's slabs by :func:`dipnet.preprocessing.recorded.read_raw_recording`.

Every source's measurement ends in :func:`finish_dips`: checked against the grid
(:func:`~dipnet.preprocessing.validation.validate_measurement`), then symmetrised once
(:func:`~dipnet.preprocessing.symmetry.apply_symmetry`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

import torch

from dipnet.core.framing import measurement_extent
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.keywords import forwards_to
from dipnet.core.measurement import DipMeasurement, MeasurementFileError
from dipnet.core.rawscan import RawScan, naming_file
from dipnet.preprocessing.recorded import finish_measurement, prepare_recording, read_raw_recording
from dipnet.preprocessing.symmetry import apply_symmetry
from dipnet.preprocessing.truth import recorded_shape_spec
from dipnet.preprocessing.validation import ValidationReport, validate_measurement

if TYPE_CHECKING:
    from dipnet.shapes import Shape

log = logging.getLogger(__name__)

#: options of :func:`read_raw_recording` that are not :func:`prepare_recording`'s
_READ_KEYS = ("t_start", "smooth", "symmetry", "interpolate")


@dataclass
class Acquisition:
    """What a source's ``measure`` hands the job.

    Attributes:
        measurement: the finished measurement (checked, then symmetrised).
        validation: the checks of the measured dips (before symmetry).
        raw: the raw scan made by this run (simulated dips; ``None`` when read from a file).
        planning: the plan's report (an adaptive loop's ``{"stop_reason", "history"}``) or ``None``.
    """

    measurement: DipMeasurement
    validation: ValidationReport
    raw: RawScan | None = None
    planning: dict[str, Any] | None = None


@dataclass
class Recording:
    """What a source's ``record`` hands self-calibration (:func:`dipnet.calibration.self_calibration.self_calibrate`).

    Attributes:
        raw: the raw scan (in the rig's commanded coordinates).
        initial: the configured rig geometry (``None``: the ideal rig).
        smooth: whether profiles get the paper's 5-tap Gaussian.
        finish: applied to every trial measurement (symmetry, interpolation), or ``None``.
        new: the raw scan was made by this run (to be saved with it).
    """

    raw: RawScan
    initial: RigGeometry | None = None
    smooth: bool = False
    finish: Callable[[DipMeasurement], DipMeasurement] | None = None
    new: bool = False


def finish_dips(measured: DipMeasurement, grid: Grid, symmetry: Mapping | None = None
                ) -> tuple[DipMeasurement, ValidationReport]:
    """``(measurement symmetrised by symmetry, the checks of the measured dips)``: the last step of every source."""
    validation = validate_measurement(measured, grid)
    return apply_symmetry(measured, symmetry), validation


@forwards_to(read_raw_recording)
def read_recorded(path: str, grid: Grid, n_slabs: int | None = None, **options) -> DipMeasurement:
    """Read a recorded measurement for reconstruction on ``grid``.

    Args:
        path: ``.npz`` measurement, ``.jsonl`` raw scan or the authors' ``.csv``.
        grid, n_slabs: the reconstruction grid and slab count (raw recordings are resampled).
        options: preprocessing options for raw recordings (see
            :func:`dipnet.preprocessing.recorded.read_raw_recording`: cross-section, smoothing, symmetry...).
    """
    p = Path(path)
    if not p.is_file():
        raise MeasurementFileError(f"measurement file not found: {p}")
    if p.suffix.lower() == ".npz":
        edges = torch.linspace(-grid.extent / 2, grid.extent / 2, (n_slabs or grid.n) + 1, dtype=torch.float64)
        measurement = DipMeasurement.load(p).rebinned(edges)
        measurement.metadata = {**measurement.metadata, "path": str(p)}  # validation messages name the file
        return measurement
    check_measurement_suffix(p)
    with naming_file(p):
        return read_raw_recording(p, grid, n_slabs, **options)


#: The file types :func:`read_recorded` reads: a dipnet measurement, a raw scan, the authors' robot CSV.
MEASUREMENT_SUFFIXES = (".npz", ".jsonl", ".csv")


def check_measurement_suffix(path: Path) -> None:
    """Refuse a file that is not one of :data:`MEASUREMENT_SUFFIXES` (by its suffix).

    Raises:
        MeasurementFileError: another file type (e.g. a mesh given as a recording).
    """
    if path.suffix.lower() not in MEASUREMENT_SUFFIXES:
        raise MeasurementFileError(f"{path}: unknown measurement file type {path.suffix!r} (expected "
                                   f"{', '.join(MEASUREMENT_SUFFIXES)}; a mesh is read with shape=mesh shape.path=...)")


class RecordedSource:
    """A recording read from a file: the dips, their directions, noise and object are the file's.

    Args:
        reader: :func:`read_recorded` with the file's ``path`` and its preprocessing options bound
            (a :func:`functools.partial`), called as ``reader(grid=, n_slabs=)``.
    """

    def __init__(self, reader: partial) -> None:
        if not isinstance(reader, partial) or "path" not in reader.keywords:
            raise TypeError("reader must be read_recorded with its path bound (a functools.partial)")
        self.reader = reader
        self.path = Path(reader.keywords["path"])
        check_measurement_suffix(self.path)  # before anything reads it (the grid's extent, the truth it names)

    def truth(self, configured: Callable[[], Shape] | None = None,
              build: Callable[[dict], Shape] | None = None) -> Shape | None:
        """The shape the recording names (fake-rig scans, :mod:`dipnet.preprocessing.truth`), built by
        ``build(spec)`` (the job's ``hydra.utils.instantiate``), else ``None``; the configured shape is not
        the recorded object and is not built."""
        spec = recorded_shape_spec(self.path)
        if spec is None or build is None:
            return None
        shape = build(spec)
        log.info("%s names its shape (%s, radius %.1f mm): scoring against it", self.path, shape.name, shape.radius())
        return shape

    def extent_mm(self) -> float | None:
        """The slabs' extent of a saved ``.npz`` measurement (:func:`~dipnet.core.framing.measurement_extent`)."""
        return measurement_extent(self.path)

    def measure(self, plan, grid: Grid, n_slabs: int, *, symmetry: Mapping | None = None,
                **unused) -> Acquisition:
        """Read the file onto ``grid``'s slabs, then check and symmetrise it (:func:`finish_dips`).
        The file fixes the dips: ``plan`` and the simulation options (``unused``) play no part."""
        measurement, validation = finish_dips(self.reader(grid=grid, n_slabs=n_slabs), grid, symmetry)
        return Acquisition(measurement, validation)

    def record(self, plan, grid: Grid, n_slabs: int, *, symmetry: Mapping | None = None, **unused) -> Recording:
        """The raw recording made ready for self-calibration (:func:`~dipnet.preprocessing.recorded.prepare_recording`
        with the reader's options); every trial measurement is symmetrised and interpolated as the reader would."""
        options = dict(self.reader.keywords)
        if self.path.suffix.lower() not in (".jsonl", ".csv"):
            raise ValueError(f"self-calibration needs a raw recording (.jsonl or .csv), not {self.path}")
        if options.get("t_start", "geometry") != "geometry":
            raise ValueError("self-calibration places the dips with the rig geometry: set the reader's t_start to "
                             "'geometry' (source.reader.t_start=geometry)")
        raw, initial, _ = prepare_recording(self.path, **{k: v for k, v in options.items()
                                                         if k != "path" and k not in _READ_KEYS})
        finish = partial(finish_measurement, symmetry=symmetry or options.get("symmetry"),
                         interpolate=options.get("interpolate"))
        return Recording(raw, initial, smooth=bool(options.get("smooth", True)), finish=finish)
