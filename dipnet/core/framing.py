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

import torch

from dipnet.core.measurement import DipMeasurement


def extent_around(radius_mm: float, resolution: int, fill: float) -> float:
    """Grid side (mm) whose working ball has radius ``radius_mm / fill`` at ``resolution`` voxels."""
    if not radius_mm > 0:
        raise ValueError(f"object radius must be positive (mm), got {radius_mm!r}")
    if not 0 < fill <= 1:
        raise ValueError(f"fill must be in (0, 1], got {fill!r}")
    return 2.0 * resolution * radius_mm / (fill * (resolution - 2))


def smallest_fill(radius_mm: float, volume: float, resolution: int, ndim: int) -> float:
    """The smallest ``fill`` at which an object of bounding radius ``radius_mm`` and volume ``volume`` (mm^3, an
    area in mm^2 in 2D) holds one voxel of the grid :func:`extent_around` chooses: below it the grid is so large that
    the whole object is less than a voxel, which the measurement's check refuses as a unit slip. The voxel's side is
    ``2 r / (fill (N - 2))``, so ``fill >= 2 r / ((N - 2) volume^(1/ndim))``."""
    return 2.0 * radius_mm / ((resolution - 2) * volume ** (1.0 / ndim))


def measurement_extent(path: str | Path) -> float | None:
    """The extent (mm) of the slabs of a saved ``.npz`` measurement (twice the largest ``|t|``
    its slabs reach), or ``None`` for other files (raw recordings need ``extent_mm``)."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        return None
    m = DipMeasurement.load(path)  # a clear error when missing or malformed
    misplaced = misplaced_dips(m)
    if misplaced:
        raise ValueError(f"{path}: the slabs of dip(s) {misplaced} lie far from where one rigid object puts them "
                         "(their volume's centre is off the other dips' plane c . theta by more than half the "
                         "object's size): a wrong offset? Fix or drop those dips")
    top = m.offsets + m.n_slabs * m.slab_thickness
    return 2.0 * float(max(m.offsets.abs().max(), top.abs().max()))


def misplaced_dips(m: DipMeasurement, min_dips: int = 6) -> list[int]:
    """The dips whose volume's centre height (mm) is off the rigid object's ``c . theta + t0`` by more
    than half the object's size (the median half-width of the dips' occupied slabs): a wrong offset.

    ``c`` and ``t0`` are fitted by least squares, the worst dip left out while it is off, at most a
    quarter of the dips; fewer than ``min_dips`` dips are not judged.
    """
    k = m.n_orientations
    if k < max(min_dips, m.ndim + 2):
        return []
    p = m.profiles.double().clamp(min=0.0)
    totals = p.sum(1)
    heights = (torch.arange(m.n_slabs, dtype=torch.float64) + 0.5) * m.slab_thickness
    centres = m.offsets.double() + (p @ heights) / totals.clamp(min=1e-300)
    occupied = p > 0.01 * p.max(1, keepdim=True).values
    first = occupied.double().argmax(1)
    last = m.n_slabs - 1 - occupied.flip(1).double().argmax(1)
    half = float(((last - first + 1).double() * m.slab_thickness / 2).median())
    design = torch.cat([m.directions.double(), torch.ones(k, 1, dtype=torch.float64)], dim=1)
    keep = totals > 0
    out: list[int] = []
    while len(out) < k // 4:
        solution = torch.linalg.lstsq(design[keep], centres[keep, None]).solution
        off = (centres - (design @ solution)[:, 0]).abs().masked_fill(~keep, 0.0)
        worst = int(off.argmax())
        if float(off[worst]) <= half:
            break
        out.append(worst)
        keep[worst] = False
    return sorted(out)
