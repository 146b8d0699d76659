"""Reconstruction quality: IoU, surface distances (Chamfer / Hausdorff), volume error.

Surface distances follow the paper's METRO-style numbers: points are sampled uniformly
(seeded) on each surface - marching-cubes meshes in 3D, iso-contours in 2D, or the truth
mesh when one is given - and measured against the other surface (exact point-to-surface
distances); the symmetric mean (Chamfer) and maximum (Hausdorff) are divided by the diagonal of the truth's bounding
box, so they are dimensionless. All functions are pure and return plain Python floats.
"""

from __future__ import annotations

import logging
from typing import Union

import igl
import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from dipnet.core.warn import log_and_warn
from dipnet.shapes.base import Shape
from dipnet.shapes.isosurface import volume_to_contours, volume_to_mesh
from dipnet.core.grid import Grid, as_grid
from dipnet.core.reconstruction import Reconstruction

log = logging.getLogger(__name__)

DEFAULT_POINTS = 20_000
_SEGMENT_CANDIDATES = 8
EMPTY_DISTANCE = 1.0  # reported Chamfer / Hausdorff (in truth diagonals) when a surface is empty


def _numpy(volume: np.ndarray | torch.Tensor) -> np.ndarray:
    return volume.detach().cpu().numpy() if isinstance(volume, torch.Tensor) else np.asarray(volume)


def _binary(volume: np.ndarray | torch.Tensor, name: str) -> np.ndarray:
    """``volume`` as a boolean array: booleans, or numbers that are all 0 or 1. Other values (occupancy
    fractions, raw least-squares values) raise a ``ValueError`` naming ``name``: cast to bool, every
    non-zero voxel would count as inside."""
    values = _numpy(volume)
    if values.dtype != bool and not np.isin(values, (0, 1)).all():
        finite = values[np.isfinite(values)] if np.issubdtype(values.dtype, np.floating) else values
        span = f"{finite.min():.3g} to {finite.max():.3g}" if finite.size else "no finite value"
        raise ValueError(f"{name} must be a boolean volume (inside / outside), got values other than 0 and 1 "
                         f"({span}): threshold it first, e.g. Reconstruction.binary or occupancy > 0.5")
    return values.astype(bool)


def iou(a: np.ndarray | torch.Tensor, b: np.ndarray | torch.Tensor) -> float:
    """Intersection over union of a boolean volume ``a`` with a reference ``b`` of one shape;
    NaN (undefined, ``null`` in ``metrics.json``) when the reference is empty: there is nothing
    to overlap, and an empty ``a`` must not score a perfect 1.0. Both must be boolean (or hold only 0
    and 1): occupancy fractions raise a ``ValueError`` (threshold them first)."""
    a, b = _binary(a, "iou: a"), _binary(b, "iou: b")
    if a.shape != b.shape:
        raise ValueError(f"iou needs volumes of one shape, got {a.shape} and {b.shape}")
    if not b.any():
        return float("nan")
    return float(np.logical_and(a, b).sum() / np.logical_or(a, b).sum())


def overlap_undefined_reason(grid: Grid) -> str:
    """Why IoU and the false rates are undefined when the truth's voxelisation is empty (``grid``:
    its voxels per axis and their size in mm)."""
    return (f"the truth is thinner than a voxel at this resolution ({grid.n} voxels of {grid.voxel_size:.3g} mm "
            "per axis) or off the grid: no voxel of it is inside")


def volume_error(recon: np.ndarray | torch.Tensor, truth_volume: float, grid: Grid) -> float:
    """Signed relative volume error ``(V_recon - V_truth) / V_truth`` of a boolean volume.

    Args:
        recon: boolean volume (or only 0 and 1; other values raise a ``ValueError``), ``grid.shape``.
        truth_volume: the true volume in mm^3 (mm^2 in 2D), positive.
        grid: the grid (for the voxel volume).
    """
    if not truth_volume > 0:
        raise ValueError(f"truth_volume must be positive, got {truth_volume}")
    return float(_binary(recon, "volume_error: recon").sum() * grid.voxel_volume / truth_volume - 1.0)


Surface = Union[trimesh.Trimesh, list, np.ndarray]
"""A surface: a 3D mesh, a list of 2D polylines ``(P, 2)`` (contours), or a point set ``(n, d)``."""


def sample_mesh(mesh: trimesh.Trimesh, n_points: int = DEFAULT_POINTS, seed: int = 0) -> np.ndarray:
    """``n_points`` points uniform on a mesh's surface, ``(n, 3)`` mm; ``(0, 3)`` if it has no faces."""
    if len(mesh.faces) == 0:
        return np.zeros((0, 3))
    points, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    return np.asarray(points, dtype=np.float64)


def _segments(lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points ``(S, 2)`` of the polylines' segments."""
    if not lines:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate([c[:-1] for c in lines]), np.concatenate([c[1:] for c in lines])


def _sample_polylines(lines: list[np.ndarray], n_points: int, seed: int) -> np.ndarray:
    """``n_points`` points uniform along polylines ``(P_i, 2)``, ``(n, 2)``."""
    a, b = _segments(lines)
    length = np.linalg.norm(b - a, axis=1)
    if length.sum() == 0:
        return np.zeros((0, 2))
    rng = np.random.default_rng(seed)
    seg = rng.choice(len(a), size=n_points, p=length / length.sum())
    u = rng.random((n_points, 1))
    return a[seg] + u * (b[seg] - a[seg])


def sample_surface(surface: Surface, n_points: int = DEFAULT_POINTS, seed: int = 0) -> np.ndarray:
    """Points uniform on ``surface`` (seeded), ``(n, d)``; a point set is returned as it is."""
    if isinstance(surface, trimesh.Trimesh):
        return sample_mesh(surface, n_points, seed)
    if isinstance(surface, list):
        return _sample_polylines(surface, n_points, seed)
    return np.asarray(surface, dtype=np.float64)


def distance_to_surface(points: np.ndarray, surface: Surface) -> np.ndarray:
    """Distance (mm) from each of ``points`` ``(n, d)`` to ``surface``, ``(n,)``.

    Exact point-to-triangle distances for a mesh (libigl's AABB tree), exact point-to-segment
    distances for polylines, nearest-point distances for a point set.
    """
    if isinstance(surface, trimesh.Trimesh):
        sq, _, _ = igl.point_mesh_squared_distance(
            np.ascontiguousarray(points, np.float64), np.ascontiguousarray(surface.vertices, np.float64),
            np.ascontiguousarray(surface.faces, np.int64))
        return np.sqrt(sq)
    if isinstance(surface, list):
        a, b = _segments(surface)
        # segments are short (marching squares: < 1.5 voxels), so the nearest one is among
        # those with the nearest midpoints
        _, idx = cKDTree((a + b) / 2).query(points, k=min(_SEGMENT_CANDIDATES, len(a)))
        idx = idx.reshape(len(points), -1)
        sa, sb = a[idx], b[idx]  # (n, k, 2)
        ab = sb - sa
        u = np.clip(np.einsum("nkd,nkd->nk", points[:, None] - sa, ab)
                    / np.maximum(np.einsum("nkd,nkd->nk", ab, ab), 1e-300), 0.0, 1.0)
        return np.linalg.norm(sa + u[..., None] * ab - points[:, None], axis=-1).min(1)
    return cKDTree(np.asarray(surface, dtype=np.float64)).query(points)[0]


def volume_surface(volume: np.ndarray | torch.Tensor, grid: Grid, level: float = 0.5) -> Surface:
    """The iso-surface ``volume == level``: a marching-cubes mesh in 3D, contours in 2D (mm)."""
    vol = _numpy(volume).astype(np.float64)
    return volume_to_mesh(vol, grid, level) if grid.ndim == 3 else volume_to_contours(vol, grid, level)


def surface_points(volume: np.ndarray | torch.Tensor, grid: Grid, n_points: int = DEFAULT_POINTS,
                   seed: int = 0, level: float = 0.5) -> np.ndarray:
    """Points uniform on the iso-surface ``volume == level`` (3D: marching cubes; 2D: contours).

    Args:
        volume: ``grid.shape``, boolean or float (larger inside).
    Returns:
        ``(n_points, ndim)`` float64 points ``(x, y[, z])`` in mm, ``(0, ndim)`` when empty.
    """
    return sample_surface(volume_surface(volume, grid, level), n_points, seed)


def chamfer_hausdorff(truth: Surface, other: Surface, n_points: int = DEFAULT_POINTS,
                      seed: int = 0) -> dict[str, float | bool | None]:
    """Symmetric surface distances between ``truth`` and ``other``, in truth bounding-box diagonals.

    METRO-style: ``n_points`` seeded samples on each surface, and each sample's distance to
    the *other surface* (exact for meshes and polylines, so identical surfaces give 0).

    Args:
        truth, other: meshes (3D), lists of polylines (2D) or point sets ``(n, d)``, in mm.
    Returns:
        ``{"chamfer": mean of the two mean distances, "hausdorff": the larger of the two
        maximum distances, "empty": whether either surface is empty}``. With an empty
        ``other`` both distances are :data:`EMPTY_DISTANCE` (finite, and as bad as one diagonal);
        with an empty ``truth`` they are ``None`` (no truth to measure against).
    """
    pa, pb = sample_surface(truth, n_points, seed), sample_surface(other, n_points, seed + 1)
    if len(pa) == 0:
        return {"chamfer": None, "hausdorff": None, "empty": True}
    if len(pb) == 0:
        return {"chamfer": EMPTY_DISTANCE, "hausdorff": EMPTY_DISTANCE, "empty": True}
    diag = float(np.linalg.norm(pa.max(0) - pa.min(0)))
    if diag == 0:
        raise ValueError("the truth surface has a zero-size bounding box")
    d_ab, d_ba = distance_to_surface(pa, other), distance_to_surface(pb, truth)
    return {"chamfer": float((d_ab.mean() + d_ba.mean()) / 2 / diag),
            "hausdorff": float(max(d_ab.max(), d_ba.max()) / diag), "empty": False}


def evaluate(reconstruction: Reconstruction, truth_occupancy: np.ndarray | torch.Tensor, grid: Grid,
             truth_mesh: trimesh.Trimesh | None = None, n_points: int = DEFAULT_POINTS,
             seed: int = 0, truth_volume: float | None = None, truth_level: float = 0.5
             ) -> dict[str, float | bool | None]:
    """IoU, Chamfer, Hausdorff and volume error of a reconstruction against the truth.

    Args:
        reconstruction: the solver's result; its surface is its refitted mesh when it has one
            (:attr:`Reconstruction.mesh`), else the iso-surface of the raw occupancy at its threshold (the
            boundary of :attr:`Reconstruction.binary`); IoU and the volume error are the binary volume's.
        truth_occupancy: true occupancy fractions in ``[0, 1]`` (other values raise a ``ValueError``), ``grid.shape``;
            inside is ``> 0.5``.
        grid: the grid of both volumes: the reconstruction's (another raises a ``ValueError``).
        truth_mesh: optional true surface in grid mm coordinates (3D); when given, the truth
            points and the true volume come from it rather than from voxels.
        n_points: surface samples per surface; seed: their random seed.
        truth_volume: the exact true volume (mm^3, e.g. ``Shape.volume``); overrides the
            mesh's or the voxels' volume as the reference of ``volume_error``.
        truth_level: occupancy above which a truth voxel is inside, for IoU (see
            :func:`reference_level`).
    Returns:
        JSON-friendly dict: ``iou`` (NaN, with a warning and the reason in ``overlap_undefined``,
        when no truth voxel is inside: an object thinner than a voxel), ``chamfer``, ``hausdorff``
        (truth diagonals; ``None``, with a warning, when the truth has no surface on ``grid``: an
        object smaller than the grid resolves), ``volume_error`` (signed, relative), ``empty``
        (the reconstruction has no voxel inside).
    """
    if not isinstance(reconstruction, Reconstruction) or isinstance(truth_occupancy, Shape):
        raise TypeError(f"evaluate(reconstruction, truth_occupancy, grid) takes a Reconstruction (a solver's result) "
                        f"and the true occupancy on its grid, got {type(reconstruction).__name__} and "
                        f"{type(truth_occupancy).__name__}: voxelise a true shape with shape.occupancy(grid)")
    grid = as_grid(grid)
    if not reconstruction.grid.matches(grid):
        raise ValueError(f"evaluate: the reconstruction is on {reconstruction.grid}, the truth on {grid}: their voxels "
                         "are not the same places; voxelise the truth on the reconstruction's grid "
                         "(shape.occupancy(reconstruction.grid))")
    truth = _numpy(truth_occupancy).astype(np.float64)
    if not (np.isfinite(truth).all() and truth.min(initial=0.0) >= 0.0 and truth.max(initial=0.0) <= 1.0):
        finite = truth[np.isfinite(truth)]
        span = f"{finite.min():.3g} to {finite.max():.3g}" if finite.size else "no finite value"
        hint = f" (a 0/{finite.max():.3g} mask? divide it by {finite.max():.3g})" \
            if finite.size and finite.max() > 1 else ""
        raise ValueError(f"evaluate: truth_occupancy must hold occupancy fractions in [0, 1], got {span}"
                         f"{' and NaN or inf' if finite.size < truth.size else ''}: the true volume and surface are "
                         f"read from them{hint}")
    binary = reconstruction.binary
    exact_volume = truth_volume
    if truth_mesh is not None:
        truth_surface, truth_volume = truth_mesh, abs(float(truth_mesh.volume))
    else:
        truth_surface, truth_volume = volume_surface(truth, grid), float(truth.sum() * grid.voxel_volume)
    if exact_volume is not None:
        truth_volume = float(exact_volume)
    recon_surface = reconstruction.mesh if reconstruction.mesh is not None else \
        volume_surface(reconstruction.occupancy, grid, level=reconstruction.threshold)
    dist = chamfer_hausdorff(truth_surface, recon_surface, n_points, seed)
    if dist["chamfer"] is None:
        message = (f"the true shape has no surface on the grid ({grid.n} voxels per axis over {grid.extent:g} mm, "
                   f"no voxel more than half inside): it is smaller than the grid resolves, so Chamfer and "
                   "Hausdorff are null; use a smaller extent_mm or a higher resolution")
        log_and_warn(log, message, stacklevel=2)
    scores = {"iou": iou(binary, truth > truth_level), "chamfer": dist["chamfer"], "hausdorff": dist["hausdorff"],
              "volume_error": volume_error(binary, truth_volume, grid), "empty": not bool(binary.any())}
    if np.isnan(scores["iou"]):
        scores["overlap_undefined"] = overlap_undefined_reason(grid)
        message = (f"{scores['overlap_undefined']}, so IoU and the false rates are undefined (null), not a score; "
                   "use a higher resolution or a smaller extent_mm")
        log_and_warn(log, message, stacklevel=2)
    return scores


def false_rates(recon: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """False-positive and false-negative voxels as fractions of the true volume (paper Fig. 13b);
    both NaN (undefined) when ``truth`` is empty, as :func:`iou`.

    Args:
        recon, truth: boolean volumes of one shape (or only 0 and 1; other values raise a ``ValueError``).
    """
    recon, truth = _binary(recon, "false_rates: recon"), _binary(truth, "false_rates: truth")
    n = int(truth.sum())
    if n == 0:
        return {"false_positive": float("nan"), "false_negative": float("nan")}
    return {"false_positive": float((recon & ~truth).sum() / n), "false_negative": float((~recon & truth).sum() / n)}


#: The IoU reference (the supersampled truth occupancy thresholded at 0.5) may differ from the
#: exact volume by at most this fraction before a job warns that its IoU is unreliable.
REFERENCE_VOLUME_TOL = 0.005


def reference_level(truth_occupancy: np.ndarray | torch.Tensor, grid: Grid, exact_volume: float) -> float:
    """The occupancy level whose ``>`` voxels hold the exact volume ``exact_volume`` (mm^3) to
    within one voxel: the binary reference of IoU and false rates. A fixed 0.5 is off by 4-6%
    for a 52 mm box at 24-40 voxels per axis (faces between supersamples); ranking the
    partial volumes and keeping as many voxels as the exact volume needs is not."""
    values, counts = np.unique(_numpy(truth_occupancy).astype(np.float64).ravel(), return_counts=True)
    if values.size < 2:
        return 0.5
    above = counts[::-1].cumsum()[::-1][1:]  # voxels above the midpoint between values i and i+1
    best = int(np.argmin(np.abs(above - exact_volume / grid.voxel_volume)))
    return float(0.5 * (values[best] + values[best + 1]))


def reference_check(truth_occupancy: np.ndarray | torch.Tensor, grid: Grid, exact_volume: float,
                    level: float) -> dict[str, float]:
    """How far the voxel references are from the exact volume (mm^3), relative:
    ``truth_voxel_volume_error`` (the partial-volume sum) and ``truth_binary_volume_error``
    (the voxels above ``level``, the reference of IoU). Warns (logging and :mod:`warnings`)
    when the binary reference is off by more than :data:`REFERENCE_VOLUME_TOL` but not empty
    (an empty one: :func:`evaluate` warns that IoU is undefined)."""
    truth = _numpy(truth_occupancy).astype(np.float64)
    partial = float(truth.sum() * grid.voxel_volume) / exact_volume - 1.0
    binary = float((truth > level).sum() * grid.voxel_volume) / exact_volume - 1.0
    if REFERENCE_VOLUME_TOL < abs(binary) and binary > -1.0:  # -1 (empty): IoU is undefined, see evaluate
        message = (f"the IoU reference voxelisation is {100 * binary:+.1f}% off the exact volume at "
                   f"{grid.n} voxels per axis: IoU and false rates are approximate; volume_error uses the exact volume")
        log_and_warn(log, message, stacklevel=2)
    return {"truth_voxel_volume_error": partial, "truth_binary_volume_error": binary, "truth_level": level}
