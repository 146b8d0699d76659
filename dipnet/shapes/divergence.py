"""Exact volume below a plane for a closed boundary (triangles in 3D, segments in 2D).

By the divergence theorem with the field ``F = (x . theta - h) theta`` (``div F = 1``, and
``F = 0`` on the cutting plane, so the cut face has no flux), the volume of ``{x . theta < h}``
inside a closed, outward-oriented boundary is

    V(h) = sum over boundary simplices S of (theta . n_S |S|) * J_S(h),
    J_S(h) = (1/|S|) * integral over the part of S below the plane of (x . theta - h).

``f = x . theta - h`` is linear, so ``J_S`` has a closed form in the sorted vertex heights
``lo <= mid <= hi`` of the simplex (piecewise polynomial in ``h``):

* triangle: 0 for ``h <= lo``; ``-(h-lo)^3 / (3 (mid-lo)(hi-lo))`` for ``lo < h <= mid``;
  ``mean - h - (hi-h)^3 / (3 (hi-lo)(hi-mid))`` for ``mid < h <= hi``; ``mean - h`` above.
* segment: 0 for ``h <= lo``; ``-(h-lo)^2 / (2 (hi-lo))`` for ``lo < h <= hi``; ``mean - h`` above.

Its derivative ``dV/dh`` is the cross-section ``a(h)`` of the region at the plane (mm^2; a
length in 2D), with ``J_S'`` in closed form too.

:class:`PlaneSweep` sorts the simplices of a chunk of directions once (vertex heights, and the
simplices by ``hi`` with cumulative sums of ``w`` and ``w * mean``); then every evaluation at
any heights costs ``O(F log H + pairs)`` per direction, where *pairs* are the (simplex, height)
pairs whose plane cuts the simplex. Everything is vectorised over the directions of the chunk
(batched ``searchsorted``), so thousands of directions cost a few numpy calls per chunk.
"""

from __future__ import annotations

import numpy as np
import torch

_CHUNK_ELEMENTS = 1 << 21  # directions x simplices per chunk of boundary_volume_below (memory)


def simplex_weights(simplices: np.ndarray) -> np.ndarray:
    """Outward normal times size of each boundary simplex.

    Args:
        simplices: (F, 3, 3) triangles (counter-clockwise seen from outside) or (F, 2, 2)
            segments (the region on their left, i.e. counter-clockwise outer rings), mm.

    Returns:
        (F, d) float64: area vectors of triangles (mm^2) / outward normals times lengths (mm).
    """
    s = np.asarray(simplices, dtype=np.float64)
    if s.shape[1:] == (3, 3):
        return 0.5 * np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0])
    if s.shape[1:] == (2, 2):
        e = s[:, 1] - s[:, 0]
        return np.stack([e[:, 1], -e[:, 0]], axis=1)
    raise ValueError(f"simplices must have shape (F, 3, 3) or (F, 2, 2), got {s.shape}")


class PlaneSweep:
    """Exact ``V(h)`` and cross-section ``a(h) = dV/dh`` of a boundary along ``K`` directions.

    Args:
        simplices: (F, 3, 3) outward-oriented triangles or (F, 2, 2) segments, mm.
        directions: (K, d) unit "up" vectors.
        weights: :func:`simplex_weights` of ``simplices`` when already known.

    Memory: about ``80 K F`` bytes for the sorted tables.
    """

    def __init__(self, simplices: np.ndarray, directions: np.ndarray, weights: np.ndarray | None = None) -> None:
        s = np.asarray(simplices, dtype=np.float64)
        theta = np.asarray(directions, dtype=np.float64)
        w = simplex_weights(s) if weights is None else weights
        n_vert = s.shape[1]
        heights = (s.reshape(-1, s.shape[2]) @ theta.T).reshape(len(s), n_vert, len(theta))
        d = np.sort(heights.transpose(2, 0, 1), axis=2)  # (K, F, n) sorted vertex heights
        self.triangles = n_vert == 3
        self.lo, self.hi = np.ascontiguousarray(d[:, :, 0]), np.ascontiguousarray(d[:, :, -1])
        self.mid = np.ascontiguousarray(d[:, :, 1]) if self.triangles else None
        self.mean = d.mean(axis=2)
        self.w = theta @ w.T  # (K, F)
        by_hi = np.argsort(self.hi, axis=1, kind="stable")
        self.hi_sorted = torch.from_numpy(np.take_along_axis(self.hi, by_hi, axis=1))
        zero = np.zeros((len(theta), 1))
        w_by_hi = np.take_along_axis(self.w, by_hi, axis=1)
        self.c0 = np.concatenate([zero, np.cumsum(w_by_hi, axis=1)], axis=1)  # (K, F + 1)
        self.c1 = np.concatenate([zero, np.cumsum(np.take_along_axis(self.w * self.mean, by_hi, axis=1), axis=1)],
                                 axis=1)

    def closed(self, rel_tol: float = 1e-9) -> np.ndarray:
        """(K,) bool: the simplices' area vectors sum to zero along each direction (a closed
        boundary, up to ``rel_tol`` of their total size), so ``V`` is a true, monotone volume."""
        return np.abs(self.c0[:, -1]) <= rel_tol * np.abs(self.w).sum(axis=1)

    def volume(self, heights: np.ndarray) -> np.ndarray:
        """``V`` at ``heights`` (K, H) mm (any order) -> (K, H) float64 mm^3 (mm^2 in 2D)."""
        return self.volume_and_area(heights)[0]

    def volume_and_area(self, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``V`` and the cross-section ``dV/dh`` at ``heights`` (K, H) mm (any order): two (K, H)
        float64 arrays, mm^3 and mm^2 (mm^2 and mm in 2D)."""
        h_in = np.asarray(heights, dtype=np.float64)
        k_dirs, n_h = h_in.shape
        order = np.argsort(h_in, axis=1, kind="stable")
        hs = np.take_along_axis(h_in, order, axis=1)
        hs_t = torch.from_numpy(hs)
        rows = np.arange(k_dirs)[:, None]
        # simplices entirely below h (hi < h): w * (mean - h), slope -w
        n_full = torch.searchsorted(self.hi_sorted, hs_t, right=False).numpy()
        volume = (self.c1[rows, n_full] - hs * self.c0[rows, n_full]).ravel()
        area = -self.c0[rows, n_full].ravel()
        # (simplex, height) pairs with lo < h <= hi: the plane cuts the simplex
        i0 = torch.searchsorted(hs_t, torch.from_numpy(self.lo), right=True).numpy()
        i1 = torch.searchsorted(hs_t, torch.from_numpy(self.hi), right=True).numpy()
        counts = (i1 - i0).ravel()
        total = int(counts.sum())
        if total:
            pair = np.repeat(np.arange(counts.size), counts)  # flat (direction, simplex) index
            start = np.cumsum(counts) - counts
            hidx = i0.ravel()[pair] + (np.arange(total) - start[pair]) + (pair // self.lo.shape[1]) * n_h
            h, w = hs.ravel()[hidx], self.w.ravel()[pair]
            dl, dh = self.lo.ravel()[pair], self.hi.ravel()[pair]
            if self.triangles:
                j, dj = _triangle_j(h, dl, self.mid.ravel()[pair], dh, self.mean.ravel()[pair])
            else:
                j, dj = _segment_j(h, dl, dh)
            volume += np.bincount(hidx, weights=w * j, minlength=k_dirs * n_h)
            area += np.bincount(hidx, weights=w * dj, minlength=k_dirs * n_h)
        return _unsort(volume.reshape(k_dirs, n_h), order), _unsort(area.reshape(k_dirs, n_h), order)


def _unsort(values: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Undo the row-wise ``order`` that sorted the heights."""
    out = np.empty_like(values)
    np.put_along_axis(out, order, values, axis=1)
    return out


def _triangle_j(h, dl, dm, dh, mean) -> tuple[np.ndarray, np.ndarray]:
    """``J`` and ``J'`` of triangles cut by the plane at ``h`` (``lo < h <= hi``), all (P,)."""
    j, dj = np.empty_like(h), np.empty_like(h)
    one = h <= dm  # one vertex below the plane; its denominators are positive there
    x, den = h[one] - dl[one], (dm[one] - dl[one]) * (dh[one] - dl[one])
    j[one], dj[one] = -(x**3) / (3.0 * den), -(x**2) / den
    two = ~one
    y, den = dh[two] - h[two], (dh[two] - dl[two]) * (dh[two] - dm[two])
    j[two], dj[two] = mean[two] - h[two] - y**3 / (3.0 * den), -1.0 + y**2 / den
    return j, dj


def _segment_j(h, dl, dh) -> tuple[np.ndarray, np.ndarray]:
    """``J`` and ``J'`` of segments cut by the line at ``h`` (``lo < h <= hi``), all (P,)."""
    x = (h - dl) / (dh - dl)
    return -0.5 * x * (h - dl), -x


def boundary_volume_below(
    simplices: np.ndarray, directions: np.ndarray, heights: np.ndarray
) -> np.ndarray:
    """Volume (area in 2D) of the part of a closed region below planes, from its boundary.

    Args:
        simplices: (F, 3, 3) outward-oriented triangles or (F, 2, 2) outward-oriented segments
            (see :func:`simplex_weights`), mm.
        directions: (K, d) unit "up" vectors.
        heights: (H,) water-line heights, mm; or (K, H), one row per direction.

    Returns:
        (K, H) float64: volume of ``{x . theta_k < h_j}`` in mm^3 (mm^2 in 2D). Exact for a
        closed boundary; for an open one it is the flux of ``F`` through the given simplices.
        Directions are swept in chunks of :class:`PlaneSweep` (vectorised within a chunk).
    """
    s = np.asarray(simplices, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    heights = np.asarray(heights, dtype=np.float64)
    weights = simplex_weights(s)
    if heights.ndim == 1:
        heights = np.broadcast_to(heights, (len(directions), heights.size))
    out = np.zeros(heights.shape)
    chunk = max(1, _CHUNK_ELEMENTS // max(len(s), 1))
    for k0 in range(0, len(directions), chunk):
        sweep = PlaneSweep(s, directions[k0:k0 + chunk], weights)
        out[k0:k0 + chunk] = sweep.volume(heights[k0:k0 + chunk])
    return out
