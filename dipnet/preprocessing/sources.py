"""Recorded measurement sources, chosen by file type.

* ``.npz``: a :class:`~dipnet.core.measurement.DipMeasurement` file, re-binned onto the grid's
  ``n_slabs`` slabs (any resolution; :meth:`~dipnet.core.measurement.DipMeasurement.rebinned`);
* ``.jsonl`` (a dipnet raw scan from ``scripts/scan.py``) or ``.csv`` (the authors' robot):
  preprocessed onto the grid's slabs by :func:`dipnet.preprocessing.recorded.read_raw_recording`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement, MeasurementFileError
from dipnet.core.keywords import forwards_to
from dipnet.core.rawscan import naming_file
from dipnet.preprocessing.recorded import read_raw_recording


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
    if p.suffix == ".npz":
        edges = torch.linspace(-grid.extent / 2, grid.extent / 2, (n_slabs or grid.n) + 1, dtype=torch.float64)
        measurement = DipMeasurement.load(p).rebinned(edges)
        measurement.metadata = {**measurement.metadata, "path": str(p)}  # validation messages name the file
        return measurement
    if p.suffix in (".jsonl", ".csv"):
        with naming_file(p):
            return read_raw_recording(p, grid, n_slabs, **options)
    raise MeasurementFileError(f"{p}: unknown measurement file type {p.suffix!r} (expected .npz, .jsonl or .csv)")
