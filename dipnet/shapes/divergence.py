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

Simplices entirely below a height are summed with cumulative sums (sorted by ``hi``); only the
(simplex, height) pairs where the plane cuts the simplex are evaluated one by one, so the cost per
direction is ``O(F log F + pairs)`` instead of ``O(F H)``.
"""

from __future__ import annotations

import numpy as np


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


def boundary_volume_below(
    simplices: np.ndarray, directions: np.ndarray, heights: np.ndarray
) -> np.ndarray:
    """Volume (area in 2D) of the part of a closed region below planes, from its boundary.

    Args:
        simplices: (F, 3, 3) outward-oriented triangles or (F, 2, 2) outward-oriented segments
            (see :func:`simplex_weights`), mm.
        directions: (K, d) unit "up" vectors.
        heights: (H,) water-line heights, mm.

    Returns:
        (K, H) float64: volume of ``{x . theta_k < h_j}`` in mm^3 (mm^2 in 2D). Exact for a
        closed boundary; for an open one it is the flux of ``F`` through the given simplices.
    """
    s = np.asarray(simplices, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    heights = np.asarray(heights, dtype=np.float64)
    weights = simplex_weights(s)
    order = np.argsort(heights, kind="stable")
    hs = heights[order]
    out = np.zeros((len(directions), len(heights)))
    for k, theta in enumerate(directions):
        out[k, order] = _sorted_heights_one_direction(s, weights, theta, hs)
    return out


def _sorted_heights_one_direction(
    s: np.ndarray, weights: np.ndarray, theta: np.ndarray, hs: np.ndarray
) -> np.ndarray:
    """``V(h)`` for one direction and sorted heights ``hs`` (H,); see the module docstring."""
    d = np.sort(s @ theta, axis=1)  # (F, n) sorted vertex heights
    w = weights @ theta  # (F,)
    lo, hi = d[:, 0], d[:, -1]
    mean = d.mean(axis=1)

    # simplices entirely below h (hi < h): sum of w * (mean - h)
    by_hi = np.argsort(hi, kind="stable")
    c0 = np.concatenate([[0.0], np.cumsum(w[by_hi])])
    c1 = np.concatenate([[0.0], np.cumsum((w * mean)[by_hi])])
    n_full = np.searchsorted(hi[by_hi], hs, side="left")
    result = c1[n_full] - hs * c0[n_full]

    # (simplex, height) pairs with lo < h <= hi: the plane cuts the simplex
    i0 = np.searchsorted(hs, lo, side="right")
    i1 = np.searchsorted(hs, hi, side="right")
    counts = i1 - i0
    total = int(counts.sum())
    if total == 0:
        return result
    face = np.repeat(np.arange(len(d)), counts)
    start = np.cumsum(counts) - counts
    hidx = i0[face] + (np.arange(total) - start[face])
    h = hs[hidx]
    dl, dh = lo[face], hi[face]
    if d.shape[1] == 2:
        j = -((h - dl) ** 2) / (2.0 * (dh - dl))
    else:
        dm = d[face, 1]
        one_below = h <= dm
        # denominators are positive wherever their branch is selected; guard the other branch
        den1 = np.where(one_below, (dm - dl) * (dh - dl), 1.0)
        den2 = np.where(one_below, 1.0, (dh - dl) * (dh - dm))
        j = np.where(
            one_below,
            -((h - dl) ** 3) / (3.0 * den1),
            mean[face] - h - (dh - h) ** 3 / (3.0 * den2),
        )
    result += np.bincount(hidx, weights=w[face] * j, minlength=len(hs))
    return result
