"""Analytic shapes: ball / disk, box, box with a water-filled inner chamber, torus.

Occupancy uses exact inside tests; ``volume_below`` is closed form (ball, disk) or exact from a
polyhedral boundary (boxes, by :mod:`dipnet.shapes.divergence`). Only the torus goes through a
fine mesh for its dips (its ``volume`` is then that mesh's volume). Boxes and chamber boxes
work in 2D and 3D (the dimension is the length of ``half_sizes``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import trimesh

from dipnet.core.grid import Grid, as_grid
from dipnet.shapes.base import Shape, ShapeError, check_dips, check_supersample
from dipnet.shapes.divergence import boundary_volume_below

#: Radii (mm) a :class:`Ball` accepts: its volume and dips stay finite and non-zero in float64 (a size in
#: the wrong unit is for the simulation's size check, :func:`~dipnet.simulator.size.check_simulation`).
BALL_RADIUS_MM = (1e-12, 1e12)


def _vector(values: float | Sequence[float], ndim: int | None, what: str) -> np.ndarray:
    """A float64 vector (mm) of finite entries; a scalar is broadcast to ``ndim`` entries."""
    v = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if v.size == 1 and ndim is not None:
        v = np.full(ndim, float(v[0]))
    if v.ndim != 1 or v.size not in (2, 3) or (ndim is not None and v.size != ndim):
        raise ShapeError(f"{what} must have 2 or 3 entries (matching the shape), got {values!r}")
    if not np.isfinite(v).all():
        raise ShapeError(f"{what} must be finite numbers (mm), got {[float(x) for x in v]}")
    return v


class Ball(Shape):
    """A ball (3D) or disk (2D) of ``radius`` mm at ``center`` (its length sets the dimension)."""

    def __init__(self, radius: float, center: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        low, high = BALL_RADIUS_MM
        if not low <= radius <= high:  # NaN fails too
            raise ShapeError(f"ball radius must be a finite, positive number of mm in [{low:g}, {high:g}], "
                             f"got {radius!r}")
        self.r = float(radius)
        self.center = _vector(center, None, "center")
        self.ndim = self.center.size
        self.name = "ball" if self.ndim == 3 else "disk"
        self.volume = (4 / 3 * np.pi * self.r**3) if self.ndim == 3 else np.pi * self.r**2
        self.notes = []

    def contains(self, points: np.ndarray) -> np.ndarray:
        return np.sum((points - self.center) ** 2, axis=1) <= self.r**2

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """Closed form in ``t = h - c.theta``: cap ``pi (r^2 (t+r) - (t^3+r^3)/3)`` / segment area."""
        d, h = check_dips(directions, heights, self.ndim)
        r = self.r
        t = np.clip(h[None, :] - (d @ self.center)[:, None], -r, r)
        if self.ndim == 3:
            v = np.pi * (r**2 * (t + r) - (t**3 + r**3) / 3)
        else:
            v = r**2 * np.arccos(-t / r) + t * np.sqrt(r**2 - t**2)
        return torch.from_numpy(v)

    def radius(self) -> float:
        return float(np.linalg.norm(self.center) + self.r)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.center - self.r, self.center + self.r


class Disk(Ball):
    """A disk of ``radius`` mm at ``center`` (2D ball)."""

    def __init__(self, radius: float, center: Sequence[float] = (0.0, 0.0)) -> None:
        super().__init__(radius, center)
        if self.ndim != 2:
            raise ShapeError(f"a disk centre has 2 entries, got {center!r}")


def box_boundary(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Outward boundary of the box ``[lo, hi]``: (12, 3, 3) triangles or (4, 2, 2) segments, mm."""
    if lo.size == 3:
        m = trimesh.creation.box(extents=hi - lo)
        m.apply_translation((lo + hi) / 2)
        return np.asarray(m.vertices[m.faces], dtype=np.float64)
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


class _BoxAlgebra(Shape):
    """A box minus disjoint inner boxes (2D or 3D); exact inside test and exact dips."""

    def __init__(self, name: str, lo: np.ndarray, hi: np.ndarray, holes: list[tuple]) -> None:
        self.name = name
        self.ndim = lo.size
        self.notes = []
        self.lo, self.hi, self.holes = lo, hi, holes
        parts = [box_boundary(lo, hi)] + [box_boundary(a, b)[:, ::-1] for a, b in holes]
        self._simplices = np.concatenate(parts)
        self.volume = float(np.prod(hi - lo) - sum(np.prod(b - a) for a, b in holes))

    def occupancy(self, grid: Grid, supersample: int = 1) -> torch.Tensor:
        """Exact fraction of each voxel inside (box overlaps are products of 1D overlaps, the
        holes are disjoint and inside the box), for any valid ``supersample`` (kept for the interface, and checked
        as every shape's: :func:`~dipnet.shapes.base.check_supersample`)."""
        if as_grid(grid).ndim != self.ndim:
            raise ShapeError(f"shape {self.name!r} is {self.ndim}D but the grid is {grid.ndim}D")
        check_supersample(supersample)
        axis, h = grid.axis().numpy(), grid.voxel_size

        def overlap(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
            # per axis (index 0 = x), the covered fraction of every voxel; volumes are [z, y, x]
            parts = [np.clip(np.minimum(axis + h / 2, hi[i]) - np.maximum(axis - h / 2, lo[i]), 0, None) / h
                     for i in range(self.ndim)]
            out = parts[0]
            for part in parts[1:]:
                out = part.reshape(-1, *([1] * out.ndim)) * out
            return out

        total = overlap(self.lo, self.hi)
        for a, b in self.holes:
            total = total - overlap(np.asarray(a), np.asarray(b))
        return torch.from_numpy(np.clip(total, 0.0, 1.0)).to(torch.float32)

    def contains(self, points: np.ndarray) -> np.ndarray:
        inside = np.all((points >= self.lo) & (points <= self.hi), axis=1)
        for a, b in self.holes:
            inside &= ~np.all((points > a) & (points < b), axis=1)
        return inside

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """Exact, from the boxes' faces by the divergence theorem; (K, d), (H,) -> (K, H)."""
        d, h = check_dips(directions, heights, self.ndim)
        return torch.from_numpy(boundary_volume_below(self._simplices, d, h))

    def radius(self) -> float:
        corners = np.where(np.abs(self.lo) > np.abs(self.hi), self.lo, self.hi)
        return float(np.linalg.norm(corners))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo.copy(), self.hi.copy()


class Box(_BoxAlgebra):
    """An axis-aligned box with ``half_sizes`` (2 or 3 entries, mm) at ``center``."""

    def __init__(self, half_sizes: Sequence[float], center: Sequence[float] | None = None) -> None:
        half = _vector(half_sizes, None, "half_sizes")
        if not np.all(half > 0):
            raise ShapeError(f"box half sizes must be positive (mm), got {half_sizes!r}")
        c = np.zeros_like(half) if center is None else _vector(center, half.size, "center")
        super().__init__("box", c - half, c + half, [])


class ChamberBox(_BoxAlgebra):
    """A box (centred on the origin) with an inner chamber open to the outside by a narrow channel.

    Water fills the chamber through the channel, so dips see it as empty, while no camera sees it
    (silhouettes and visual hulls fill it). The channel is a square (3D) / slot (2D) tube of
    half-width ``channel_half_width`` running along the last axis (+z in 3D, +y in 2D) from the
    chamber's top face to the box's top face.

    Args:
        half_sizes: (d,) outer half sizes, mm (d = 2 or 3).
        chamber_half_sizes: (d,) chamber half sizes, mm (a scalar is broadcast).
        channel_half_width: mm, smaller than every chamber half size.
        chamber_center: (d,) chamber centre, mm (default the origin).
    """

    def __init__(
        self, half_sizes: Sequence[float], chamber_half_sizes: float | Sequence[float],
        channel_half_width: float, chamber_center: Sequence[float] | None = None,
    ) -> None:
        half = _vector(half_sizes, None, "half_sizes")
        d = half.size
        ch = _vector(chamber_half_sizes, d, "chamber_half_sizes")
        cc = np.zeros(d) if chamber_center is None else _vector(chamber_center, d, "chamber_center")
        w = float(channel_half_width)
        if not (np.all(half > 0) and np.all(ch > 0) and w > 0):
            raise ShapeError("chamber box sizes must be positive (mm)")
        if np.any(cc - ch <= -half) or np.any(cc + ch >= half):
            raise ShapeError("the chamber must lie strictly inside the box")
        if np.any(w >= ch[:-1]):
            raise ShapeError("the channel must be narrower than the chamber")
        chamber = (cc - ch, cc + ch)
        channel_lo = np.append(cc[:-1] - w, cc[-1] + ch[-1])
        channel_hi = np.append(cc[:-1] + w, half[-1])
        super().__init__("chamber_box", -half, half, [chamber, (channel_lo, channel_hi)])
        self.chamber = chamber


class Torus(Shape):
    """A solid torus around the z axis: major radius ``R``, tube radius ``r`` (mm), centred.

    ``occupancy`` is exact; ``volume_below`` and ``volume`` come from a fine triangle mesh
    (``sections`` around the axis, ``sections // 2`` around the tube; relative volume error
    about ``(2 pi / (sections / 2))^2 / 6``, below 2e-3 for the default).
    """

    ndim = 3

    def __init__(self, R: float, r: float, sections: int = 128) -> None:
        if not 0 < r < R:
            raise ShapeError(f"torus needs 0 < r < R (mm), got R={R!r}, r={r!r}")
        self.name = "torus"
        self.R, self.r = float(R), float(r)
        self.notes = []
        self.mesh = trimesh.creation.torus(
            major_radius=self.R, minor_radius=self.r,
            major_sections=sections, minor_sections=sections // 2,
        )
        self._simplices = np.asarray(self.mesh.vertices[self.mesh.faces], dtype=np.float64)
        self.volume = float(self.mesh.volume)

    def contains(self, points: np.ndarray) -> np.ndarray:
        rho = np.hypot(points[:, 0], points[:, 1])
        return (rho - self.R) ** 2 + points[:, 2] ** 2 <= self.r**2

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """From the fine mesh by the divergence theorem; (K, 3), (H,) -> (K, H) mm^3."""
        d, h = check_dips(directions, heights, 3)
        return torch.from_numpy(boundary_volume_below(self._simplices, d, h))

    def radius(self) -> float:
        return self.R + self.r

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        a = self.R + self.r
        return np.array([-a, -a, -self.r]), np.array([a, a, self.r])
