"""Analytic ball (3D) / disk (2D) phantom: partial-volume occupancy and exact slab volumes.

The ground truth of the operator contract and benchmark: a ball of radius ``r`` centred at
``c`` has, below height ``u`` from its centre, the volume ``pi (r^2 u - u^3 / 3) + 2 pi r^3 / 3``
(3D) or the area ``u sqrt(r^2 - u^2) + r^2 asin(u / r) + pi r^2 / 2`` (2D), so slab ``j`` of
orientation ``theta`` holds the difference of these at the slab edges minus ``theta . c``.
"""

from __future__ import annotations

import itertools
import math

import torch

from dipnet.core.grid import Grid


def ball_occupancy(grid: Grid, centre: torch.Tensor, radius: float, sub: int = 5) -> torch.Tensor:
    """Occupancy fractions of a ball (disk), ``grid.shape`` float64.

    Voxels cut by the surface get the fraction of their ``sub^d`` supersampled points inside.
    ``centre`` ``(d,)`` in mm as ``(x, y[, z])``, ``radius`` in mm.
    """
    centre = torch.as_tensor(centre, dtype=torch.float64)
    pts = grid.centers()
    dist = (pts - centre).norm(dim=-1)
    occ = (dist <= radius).to(torch.float64)
    cut = (dist - radius).abs() <= grid.voxel_size * math.sqrt(grid.ndim) / 2
    ticks = ((torch.arange(sub, dtype=torch.float64) + 0.5) / sub - 0.5) * grid.voxel_size
    offsets = torch.tensor(list(itertools.product(ticks.tolist(), repeat=grid.ndim)), dtype=torch.float64)
    inside = (pts[cut][:, None, :] + offsets - centre).norm(dim=-1) <= radius
    occ[cut] = inside.to(torch.float64).mean(dim=1)
    return occ


def ball_below(u: torch.Tensor, radius: float, ndim: int) -> torch.Tensor:
    """Volume (3D, mm^3) or area (2D, mm^2) of the ball below height ``u`` (mm) from its centre."""
    u = u.clamp(-radius, radius)
    if ndim == 3:
        return math.pi * (radius**2 * u - u**3 / 3) + 2 * math.pi * radius**3 / 3
    return u * (radius**2 - u**2).clamp(min=0).sqrt() + radius**2 * torch.asin(u / radius) + math.pi * radius**2 / 2


def ball_profiles(directions: torch.Tensor, edges: torch.Tensor, centre: torch.Tensor, radius: float) -> torch.Tensor:
    """Exact slab volumes ``(K, M)`` of the ball for unit ``directions`` ``(K, d)`` and slab
    ``edges`` ``(M + 1,)`` in mm."""
    directions = torch.as_tensor(directions, dtype=torch.float64)
    heights = directions @ torch.as_tensor(centre, dtype=torch.float64)
    cum = ball_below(edges[None, :] - heights[:, None], radius, directions.shape[1])
    return cum[:, 1:] - cum[:, :-1]
