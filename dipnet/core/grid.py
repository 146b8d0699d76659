"""The voxel grid and the project's single axis / coordinate convention.

Convention (used everywhere in dipnet)
--------------------------------------
* A volume is a tensor indexed ``[z, y, x]`` in 3D and ``[y, x]`` in 2D, matching
  ``torch.nn.functional.grid_sample``'s ``(D, H, W)`` / ``(H, W)`` layout.
* Physical coordinates are millimetres, with the grid centred on the origin. A point is
  written ``(x, y[, z])`` (the order of ``grid_sample``'s last grid dimension).
* Voxel ``i`` along an axis has its centre at ``-extent/2 + (i + 0.5) * voxel_size``.
* The *working region* is the ball of radius ``extent/2 - voxel_size`` around the origin:
  every rotation keeps it inside the grid, so operators ignore voxels outside it.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch

from dipnet.core.counts import is_real


@dataclass(frozen=True)
class Grid:
    """A cubic (3D) or square (2D) voxel grid centred on the origin.

    Args:
        n: voxels per axis (``N``).
        ndim: 2 or 3.
        extent: side length of the grid in mm: finite and positive, with a voxel volume ``(extent / n)^ndim``
            that float64 holds (normal, not infinite); otherwise a ``ValueError``.
    """

    n: int
    ndim: int = 3
    extent: float = 100.0

    def __post_init__(self) -> None:
        if isinstance(self.n, bool) or int(self.n) != self.n or self.n < 4:
            raise ValueError(f"grid resolution n must be an integer >= 4, got {self.n!r}")
        if isinstance(self.ndim, bool) or self.ndim not in (2, 3):
            raise ValueError(f"grid ndim must be 2 or 3, got {self.ndim!r}")
        if isinstance(self.extent, bool) or not 0 < self.extent < math.inf:  # NaN fails too
            raise ValueError(f"grid extent must be a finite, positive number (mm), got {self.extent!r}")
        # a whole float (15.0, a numpy integer) is stored as the int every shape and index needs
        object.__setattr__(self, "n", int(self.n))
        object.__setattr__(self, "ndim", int(self.ndim))
        object.__setattr__(self, "extent", float(self.extent))
        try:
            voxel = self.voxel_volume
        except OverflowError:
            voxel = math.inf
        if not sys.float_info.min < voxel < math.inf:
            raise ValueError(f"grid extent {self.extent:g} mm at n={self.n} gives voxels of {voxel:g} mm^{self.ndim}, "
                             "beyond float64 (profiles would be 0 or overflow): give the extent in mm")

    @property
    def shape(self) -> tuple[int, ...]:
        """Volume shape, ``(N, N)`` or ``(N, N, N)``."""
        return (self.n,) * self.ndim

    @property
    def voxel_size(self) -> float:
        """Voxel edge length in mm."""
        return self.extent / self.n

    @property
    def voxel_volume(self) -> float:
        """Voxel volume in mm^ndim (an area in 2D)."""
        return self.voxel_size**self.ndim

    @property
    def volume_unit(self) -> str:
        """The unit of a voxel's volume and of a slab's: ``"mm^3"``, or ``"mm^2"`` in 2D (slabs are areas)."""
        return f"mm^{self.ndim}"

    @property
    def radius(self) -> float:
        """Radius of the working region (mm)."""
        return self.extent / 2 - self.voxel_size

    def axis(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Voxel centre coordinates along one axis, shape ``(N,)``, in mm."""
        h = self.voxel_size
        return -self.extent / 2 + (torch.arange(self.n, dtype=dtype) + 0.5) * h

    def centers(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Voxel centres, shape ``(*shape, ndim)`` with the last axis ordered ``(x, y[, z])``, mm."""
        a = self.axis(dtype)
        mesh = torch.meshgrid(*([a] * self.ndim), indexing="ij")  # (z, y, x) order
        return torch.stack(mesh[::-1], dim=-1)

    def working_mask(self) -> torch.Tensor:
        """Boolean mask of the voxels whose centre lies in the working region, shape ``shape``."""
        return self.centers().norm(dim=-1) <= self.radius

    def matches(self, other: "Grid") -> bool:
        """Whether ``other`` has the same voxels: same ``n`` and ``ndim``, extents equal to 1e-9 relative."""
        return (self.n, self.ndim) == (other.n, other.ndim) and math.isclose(self.extent, other.extent, rel_tol=1e-9)

    def to_dict(self) -> dict:
        """Plain metadata, for files."""
        return {"n": self.n, "ndim": self.ndim, "extent": self.extent}


def slab_count(grid: Grid, n_slabs: int | None = None) -> int:
    """Slabs per profile ``M``: ``n_slabs`` as an int, ``grid.n`` when ``None``; a ``ValueError`` unless it is a
    whole number >= 2 (``24.0`` is 24, ``7.5`` is refused rather than cut to 7)."""
    if n_slabs is None:
        return grid.n
    if not is_real(n_slabs) or int(n_slabs) != n_slabs or n_slabs < 2:
        raise ValueError(f"n_slabs must be a whole number >= 2 (slabs per profile), got {n_slabs!r}")
    return int(n_slabs)


def as_grid(grid: Grid) -> Grid:
    """``grid`` itself when it is a :class:`Grid`; anything else (a resolution, a shape tuple) raises a
    ``TypeError`` saying how to make one."""
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a dipnet.Grid, e.g. Grid({grid if isinstance(grid, int) else 32}, ndim=3, "
                        f"extent=100.0) (voxels per axis, 2 or 3 dimensions, side in mm), got {grid!r}")
    return grid
