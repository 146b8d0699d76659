"""Recorded measurement sources, chosen by file type.

* ``.npz``: a :class:`~dipnet.measurement.DipMeasurement` file (solvers resample its slabs
  onto the operator's);
* ``.jsonl``: a dipnet raw scan (from ``scripts/scan.py``), preprocessed onto the grid's slabs.
"""

from __future__ import annotations

from pathlib import Path

from dipnet.grid import Grid
from dipnet.measurement import DipMeasurement, MeasurementFileError
from dipnet.preprocess import preprocess_file


def read_recorded(path: str, grid: Grid, n_slabs: int | None = None, t_start: str | float = "centroid",
                  smooth: bool = False) -> DipMeasurement:
    """Read a recorded measurement for reconstruction on ``grid``.

    Args:
        path: ``.npz`` measurement or ``.jsonl`` raw scan.
        grid, n_slabs: the reconstruction grid and slab count (raw scans are resampled onto them).
        t_start: how raw scans are placed along each direction (see :func:`dipnet.preprocess.preprocess`).
        smooth: the paper's 5-tap Gaussian on raw scans.
    """
    p = Path(path)
    if not p.is_file():
        raise MeasurementFileError(f"measurement file not found: {p}")
    if p.suffix == ".npz":
        return DipMeasurement.load(p)
    if p.suffix == ".jsonl":
        return preprocess_file(p, grid=grid, n_slabs=n_slabs, t_start=t_start, smooth=smooth)
    raise MeasurementFileError(f"{p}: unknown measurement file type {p.suffix!r} (expected .npz or .jsonl)")
