"""Surfaces of a voxel volume: marching-cubes meshes (3D) and contours (2D), in mm, the volume
they enclose, and the level at which they enclose a given volume.

Coordinates follow :mod:`dipnet.core.grid`: a volume indexed ``[z, y, x]`` (``[y, x]`` in 2D)
becomes vertices ``(x, y, z)`` (points ``(x, y)``) in mm, voxel ``i`` at
``-extent/2 + (i + 0.5) * voxel_size``.

Marching cubes and orientation: scikit-image returns vertices in array-index order
``(z, y, x)``; with its default ``gradient_direction='descent'`` (values are larger inside)
the faces wind clockwise seen from outside in that order. Reversing the vertex axes to
``(x, y, z)`` is a reflection, which flips the winding, so faces come out counter-clockwise
seen from outside: outward normals and a positive signed volume. (Keeping the ``(z, y, x)``
order would instead need ``gradient_direction='ascent'``.) The volume is padded by one voxel
so that surfaces touching the grid border still close.
"""

from __future__ import annotations


import numpy as np
import torch
import trimesh
from scipy import optimize
from skimage import measure

from dipnet.core.grid import Grid


def _as_array(volume: np.ndarray | torch.Tensor, grid: Grid) -> np.ndarray:
    vol = volume.detach().cpu().numpy() if isinstance(volume, torch.Tensor) else np.asarray(volume)
    if vol.shape != grid.shape:
        raise ValueError(f"volume must have the grid's shape {grid.shape}, got {vol.shape}")
    return vol.astype(np.float64)


def _padded(vol: np.ndarray, level: float) -> np.ndarray:
    """Pad by one voxel with a value below ``level`` (0 for occupancies) so surfaces close."""
    low = min(0.0, float(vol.min()))
    return np.pad(vol, 1, constant_values=low if low < level else level - 1.0)


def volume_to_mesh(volume: np.ndarray | torch.Tensor, grid: Grid, level: float = 0.5) -> trimesh.Trimesh:
    """Iso-surface ``volume == level`` of a 3D volume as a closed mesh in mm.

    Args:
        volume: ``grid.shape`` (``[z, y, x]``), values larger inside (occupancy, booleans).
        grid: a 3D grid.
        level: iso-value (e.g. 0.5 for occupancy, a solver's threshold for raw values).

    Returns:
        ``trimesh.Trimesh`` with vertices ``(x, y, z)`` in mm and outward normals; an empty
        mesh (no faces) when no voxel exceeds ``level``.
    """
    if grid.ndim != 3:
        raise ValueError("volume_to_mesh needs a 3D grid; use volume_to_contours in 2D")
    vol = _as_array(volume, grid)
    if not (vol > level).any():
        return trimesh.Trimesh()
    verts, faces, _, _ = measure.marching_cubes(_padded(vol, level), level=level)
    h = grid.voxel_size
    # padded index p <-> voxel p - 1, centred at -L/2 + (p - 0.5) h; (z, y, x) -> (x, y, z)
    verts_mm = (verts[:, ::-1] - 0.5) * h - grid.extent / 2
    return trimesh.Trimesh(vertices=verts_mm, faces=faces, process=False)


def volume_to_contours(image: np.ndarray | torch.Tensor, grid: Grid, level: float = 0.5) -> list[np.ndarray]:
    """Iso-contours ``image == level`` of a 2D image (``[y, x]``) as closed polylines.

    Returns:
        list of ``(P, 2)`` float64 arrays of points ``(x, y)`` in mm (first point repeated
        last); empty when no pixel exceeds ``level``.
    """
    if grid.ndim != 2:
        raise ValueError("volume_to_contours needs a 2D grid; use volume_to_mesh in 3D")
    img = _as_array(image, grid)
    if not (img > level).any():
        return []
    h = grid.voxel_size
    return [(c[:, ::-1] - 0.5) * h - grid.extent / 2 for c in measure.find_contours(_padded(img, level), level)]


def enclosed_volume(volume: np.ndarray | torch.Tensor, grid: Grid, level: float = 0.5) -> float:
    """Volume (mm^3; area in mm^2 in 2D) inside the iso-surface ``volume == level``
    (:func:`volume_to_mesh`'s mesh, :func:`volume_to_contours`' polygons, holes subtracted).

    Unlike a count of the voxels above ``level``, this moves continuously with ``level``.
    """
    if grid.ndim == 3:
        return float(volume_to_mesh(volume, grid, level).volume)
    # find_contours keeps the higher values on one side of every contour, so the shoelace areas
    # of outer boundaries and of holes have opposite signs
    area = sum(0.5 * float(np.sum(c[:-1, 0] * c[1:, 1] - c[1:, 0] * c[:-1, 1]))
               for c in volume_to_contours(volume, grid, level))
    return abs(area)


def level_for_volume(volume: np.ndarray | torch.Tensor, grid: Grid, target: float,
                     bounds: tuple[float, float] = (0.25, 0.75), xtol: float = 1e-3) -> float:
    """The iso-level in ``bounds`` whose surface encloses ``target`` (mm^3; mm^2 in 2D).

    The enclosed volume falls as the level rises, so the level is found by bisection (Brent's
    method, to ``xtol``); when even ``bounds[0]`` encloses less than ``target`` the result is
    ``bounds[0]``, when even ``bounds[1]`` encloses more, ``bounds[1]``.

    Args:
        volume: ``grid.shape``, values larger inside (an occupancy in ``[0, 1]``).
        grid: its grid.
        target: the volume the surface should enclose, > 0.
        bounds: the levels searched, ``0 < low < high < 1`` for an occupancy.
    """
    low, high = bounds
    if not low < high:
        raise ValueError(f"bounds must be increasing, got {bounds}")
    if not target > 0:
        raise ValueError(f"target volume must be positive, got {target}")
    vol = _as_array(volume, grid)

    def excess(level: float) -> float:  # decreasing in the level
        return enclosed_volume(vol, grid, level) - target

    if excess(low) <= 0:
        return float(low)
    if excess(high) >= 0:
        return float(high)
    return float(optimize.brentq(excess, low, high, xtol=xtol))
