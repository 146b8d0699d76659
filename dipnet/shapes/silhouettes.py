"""2D shapes: polygons with holes, a built-in elephant, and silhouettes of projected meshes.

A :class:`PolygonShape` is a set of closed rings under the even-odd rule (a point is inside when
an odd number of rings contains it), so outer boundaries and holes need no labels. Its area and
``volume_below`` are exact (divergence theorem on the edges); occupancy uses point-in-polygon
tests (matplotlib).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from matplotlib.path import Path
from scipy import ndimage
from skimage.draw import polygon as draw_polygon
from skimage.measure import find_contours

from dipnet.shapes.base import Shape, ShapeError, check_dips
from dipnet.shapes.divergence import boundary_volume_below
from dipnet.shapes.mesh import MeshShape


def signed_area(ring: np.ndarray) -> float:
    """Shoelace area of a closed ring (n, 2), mm^2; positive when counter-clockwise."""
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


class PolygonShape(Shape):
    """A 2D region bounded by closed rings (even-odd rule), vertices in mm.

    Args:
        rings: closed polylines, each (n, 2) with n >= 3 (repeating the first vertex at the end
            is allowed). Rings must not cross each other or themselves.
        name: a label.

    Attributes:
        rings: the rings, outer ones counter-clockwise and holes clockwise.
    """

    ndim = 2

    def __init__(self, rings: Sequence[np.ndarray], name: str = "polygon") -> None:
        self.name = name
        self.notes = []
        clean = []
        for ring in rings:
            r = np.asarray(ring, dtype=np.float64)
            if r.ndim != 2 or r.shape[1] != 2:
                raise ShapeError(f"polygon {name!r}: a ring must have shape (n, 2), got {r.shape}")
            if len(r) > 1 and np.allclose(r[0], r[-1]):
                r = r[:-1]
            if len(r) >= 3 and abs(signed_area(r)) > 0:
                clean.append(r)
        if not clean:
            raise ShapeError(f"polygon {name!r} has no ring with a positive area")
        self._paths = [Path(r) for r in clean]
        depth = [
            sum(p.contains_point(r[0]) for j, p in enumerate(self._paths) if j != i)
            for i, r in enumerate(clean)
        ]
        self.rings = [
            r if (signed_area(r) > 0) == (k % 2 == 0) else r[::-1] for r, k in zip(clean, depth)
        ]
        self.volume = float(sum(signed_area(r) for r in self.rings))
        if not self.volume > 0:
            raise ShapeError(f"polygon {name!r} encloses no area")
        self._segments = np.concatenate(
            [np.stack([r, np.roll(r, -1, axis=0)], axis=1) for r in self.rings]
        )
        vertices = np.concatenate(self.rings)
        self._lo, self._hi = vertices.min(axis=0), vertices.max(axis=0)
        self._radius = float(np.linalg.norm(vertices, axis=1).max())

    def contains(self, points: np.ndarray) -> np.ndarray:
        count = np.zeros(len(points), dtype=int)
        for p in self._paths:
            count += p.contains_points(points)
        return count % 2 == 1

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """Exact area of ``{x . theta < h}``: (K, 2), (H,) -> (K, H) float64 mm^2."""
        d, h = check_dips(directions, heights, 2)
        return torch.from_numpy(boundary_volume_below(self._segments, d, h))

    def radius(self) -> float:
        return self._radius

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._lo.copy(), self._hi.copy()


# Side view of an elephant facing +x (body, four legs, head, curled trunk, tail), counter-clockwise,
# in arbitrary units; `elephant` centres and scales it.
_ELEPHANT = np.array([
    (-1.00, 0.00), (-0.92, -0.15), (-0.90, -1.00), (-0.62, -1.00), (-0.60, -0.25),
    (-0.47, -0.30), (-0.47, -1.00), (-0.22, -1.00), (-0.22, -0.30), (0.00, -0.32),
    (0.10, -0.30), (0.10, -1.00), (0.36, -1.00), (0.36, -0.28), (0.45, -0.25),
    (0.45, -1.00), (0.70, -1.00), (0.70, -0.10), (0.80, 0.05), (0.92, 0.15),
    (0.98, 0.00), (1.00, -0.40), (1.02, -0.70), (1.08, -0.82), (1.20, -0.85),
    (1.28, -0.78), (1.24, -0.72), (1.15, -0.72), (1.12, -0.60), (1.12, -0.30),
    (1.14, 0.00), (1.15, 0.30), (1.10, 0.55), (1.00, 0.80), (0.85, 0.90),
    (0.70, 0.88), (0.60, 0.75), (0.40, 0.80), (0.10, 0.85), (-0.30, 0.82),
    (-0.65, 0.70), (-0.90, 0.50), (-1.02, 0.30), (-1.04, 0.22), (-1.15, 0.00),
    (-1.18, -0.25), (-1.13, -0.25), (-1.08, -0.02), (-1.02, 0.12),
])


def elephant(radius: float) -> PolygonShape:
    """The built-in elephant: area centroid at the origin, farthest vertex at ``radius`` mm."""
    ring = _ELEPHANT - _polygon_centroid(_ELEPHANT)
    ring = ring * (radius / np.linalg.norm(ring, axis=1).max())
    return PolygonShape([ring], name="elephant")


def _polygon_centroid(ring: np.ndarray) -> np.ndarray:
    """Area centroid of a simple ring (n, 2)."""
    x, y = ring[:, 0], ring[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = cross.sum() / 2
    cx = np.sum((x + np.roll(x, -1)) * cross) / (6 * a)
    cy = np.sum((y + np.roll(y, -1)) * cross) / (6 * a)
    return np.array([cx, cy])


_PLANE_AXES = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}


def project_mesh(shape: MeshShape, axis: str = "z", pixels: int = 1024) -> PolygonShape:
    """Silhouette of a mesh seen along ``axis``: the polygon (with holes) its shadow covers.

    The projected triangles are rasterised on a ``pixels``-wide square image covering the
    shadow, and the boundary is traced with marching squares (contours at 0.5, so the ring runs
    half-way between covered and uncovered pixel centres). Holes of the shadow are kept;
    background specks under 4 pixels (rasterisation cracks between triangles) are filled.

    Args:
        shape: a mesh shape (mm).
        axis: 'x', 'y' or 'z'; the plane coordinates are (y, z), (z, x) or (x, y) respectively.
        pixels: image resolution; the boundary error is about ``span / pixels``.

    Returns:
        A :class:`PolygonShape` in the plane coordinates, mm, with the mesh's frame in the plane: ``frame_axes``
        (the file's axes the 2D ``(x, y)`` are, e.g. ``"zx"`` along ``y``), ``frame_offset`` ``(2,)`` mm (the mesh's
        ``frame_offset`` on them) and ``frame_scale``, so a 2D point ``p`` is ``(p + frame_offset) / frame_scale`` on
        those axes of the file.
    """
    if axis not in _PLANE_AXES:
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    uv = np.asarray(shape.mesh.vertices, dtype=np.float64)[:, list(_PLANE_AXES[axis])]
    pad = 2
    lo = uv.min(axis=0)
    step = float((uv.max(axis=0) - lo).max()) / (pixels - 2 * pad - 1)
    pix = (uv - lo) / step + pad  # (u, v) in pixel units; pixel (row=v, col=u) centre at integers
    image = np.zeros((pixels, pixels), dtype=bool)
    for tri in pix[np.asarray(shape.mesh.faces)]:
        rr, cc = draw_polygon(tri[:, 1], tri[:, 0], image.shape)
        image[rr, cc] = True
    labels, n = ndimage.label(~image)
    sizes = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n + 1))
    specks = np.flatnonzero(sizes < 4) + 1
    image[np.isin(labels, specks)] = True
    rings = [
        (c[:, ::-1] - pad) * step + lo
        for c in find_contours(image.astype(np.float64), 0.5)
        if len(c) >= 4 and abs(signed_area(c)) >= 2.0
    ]
    polygon = PolygonShape(rings, name=f"{shape.name}_silhouette_{axis}")
    plane = list(_PLANE_AXES[axis])
    polygon.frame_axes = "".join("xyz"[i] for i in plane)
    polygon.frame_offset = np.asarray(getattr(shape, "frame_offset", np.zeros(3)), dtype=np.float64)[plane]
    polygon.frame_scale = float(getattr(shape, "frame_scale", 1.0))
    polygon.source = getattr(shape, "source", None)
    return polygon
