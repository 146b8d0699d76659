"""Choosing the grid around the object, so that an object keeps its size in mm.

The object's size is physical (a mesh in its own units, a built-in shape of a given radius in
mm); the grid's side ``extent`` follows from it: the object's bounding radius ``r`` (around
its centre, the frame's origin) is ``fill`` of the working ball, whose radius is
``extent / 2 - voxel = extent (N - 2) / (2 N)``, so

    extent = 2 N r / (fill (N - 2)).

The same object at resolutions 24 and 40 is then the same object on two grids (only the
voxels change), and runs at different resolutions compare. A given ``extent_mm`` overrides.
"""

from __future__ import annotations

from pathlib import Path

from dipnet.core.measurement import DipMeasurement


def extent_around(radius_mm: float, resolution: int, fill: float) -> float:
    """Grid side (mm) whose working ball has radius ``radius_mm / fill`` at ``resolution`` voxels."""
    if not radius_mm > 0:
        raise ValueError(f"object radius must be positive (mm), got {radius_mm!r}")
    if not 0 < fill <= 1:
        raise ValueError(f"fill must be in (0, 1], got {fill!r}")
    return 2.0 * resolution * radius_mm / (fill * (resolution - 2))


def measurement_extent(path: str | Path) -> float | None:
    """The extent (mm) of the slabs of a saved ``.npz`` measurement (twice the largest ``|t|``
    its slabs reach), or ``None`` for other files (raw recordings need ``extent_mm``)."""
    path = Path(path)
    if path.suffix != ".npz":
        return None
    m = DipMeasurement.load(path)  # a clear error when missing or malformed
    top = m.offsets + m.n_slabs * m.slab_thickness
    return 2.0 * float(max(m.offsets.abs().max(), top.abs().max()))
