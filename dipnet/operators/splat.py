"""``splat``: the dip transform by direct splatting, with no rotated volume.

Each voxel's volume is shared linearly (a hat kernel) between the two sampling planes
nearest to its height ``t_v = x_v . theta``; planes are summed into slabs. This is exactly
what :class:`~dipnet.operators.rotate_sum.RotateSumOperator` computes (rotation by trilinear
interpolation followed by plane sums), because the in-plane interpolation weights of a voxel
sum to one: only the height matters. Cost ``O(K N^d)`` with no ``N^d``-sized temporaries
per orientation, and the explicit sparse matrix comes from the same weights.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse
import torch

from dipnet.core.grid import Grid
from dipnet.operators.base import DipOperator

_CHUNK_ELEMENTS = 1 << 22  # voxel x orientation pairs handled at once
_CACHE_BYTES = 1 << 29  # keep precomputed weights when they fit in 512 MiB


def planes_per_slab(grid: Grid, n_slabs: int) -> int:
    """Sampling planes per slab: enough that planes are no further apart than a voxel."""
    return max(1, math.ceil(grid.extent / n_slabs / grid.voxel_size - 1e-9))


class SplatOperator(DipOperator):
    """Dip transform by linear splatting of voxel heights into slabs (see module docstring)."""

    def __init__(self, grid: Grid, directions: torch.Tensor, n_slabs: int | None = None) -> None:
        super().__init__(grid, directions, n_slabs)
        self.planes = planes_per_slab(grid, self.n_slabs)
        self.register_buffer("voxel_index", torch.nonzero(self.mask.reshape(-1)).squeeze(1))
        self.register_buffer("points", grid.centers().reshape(-1, grid.ndim)[self.voxel_index])
        n_pts = self.points.shape[0]
        self._chunk = max(1, _CHUNK_ELEMENTS // n_pts)
        self._cache: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
        self._use_cache = n_pts * self.n_orientations * 24 <= _CACHE_BYTES

    # ------------------------------------------------------------------ weights
    def _chunks(self):
        """Yield ``(k0, k1, slab0, slab1, w)``: flat (k, slab) indices of the lower / upper plane
        and the upper weight, each of shape ``(n_points * (k1 - k0),)``, orientation-major."""
        if self._cache is not None:
            yield from self._cache
            return
        built = []
        for k0 in range(0, self.n_orientations, self._chunk):
            k1 = min(k0 + self._chunk, self.n_orientations)
            item = (k0, k1, *self._weights(k0, k1))
            if self._use_cache:
                built.append(item)
            yield item
        if self._use_cache:
            self._cache = built

    def _weights(self, k0: int, k1: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        step = self.slab_thickness / self.planes
        t = self.directions[k0:k1] @ self.points.T  # (kc, n_points), mm
        u = (t + self.grid.extent / 2) / step - 0.5  # plane coordinate
        n_planes = self.n_slabs * self.planes
        i0 = torch.floor(u).clamp(0, n_planes - 2)
        w = (u - i0).clamp(0.0, 1.0)
        i0 = i0.long()
        base = (torch.arange(k0, k1) * self.n_slabs).unsqueeze(1)
        s0 = base + torch.div(i0, self.planes, rounding_mode="floor")
        s1 = base + torch.div(i0 + 1, self.planes, rounding_mode="floor")
        return s0.reshape(-1), s1.reshape(-1), w.reshape(-1)

    # ------------------------------------------------------------------ application
    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        b = volume.shape[0]
        f = volume.reshape(b, -1)[:, self.voxel_index] * self.grid.voxel_volume  # (B, n_points)
        out = volume.new_zeros(b, self.n_orientations * self.n_slabs)
        for k0, k1, s0, s1, w in self._chunks():
            w = w.to(volume.dtype)
            src = f.repeat(1, k1 - k0)  # orientation-major, matches the weight layout
            out = out.index_add(1, s0, src * (1 - w)).index_add(1, s1, src * w)
        return out.reshape(b, self.n_orientations, self.n_slabs)

    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        b = profiles.shape[0]
        y = profiles.reshape(b, -1)
        n_pts = self.points.shape[0]
        acc = profiles.new_zeros(b, n_pts)
        for k0, k1, s0, s1, w in self._chunks():
            w = w.to(profiles.dtype)
            vals = y[:, s0] * (1 - w) + y[:, s1] * w  # (B, n_points * kc)
            acc = acc + vals.reshape(b, k1 - k0, n_pts).sum(1)
        out = profiles.new_zeros(b, math.prod(self.grid.shape))
        out = out.index_copy(1, self.voxel_index, acc * self.grid.voxel_volume)
        return out.reshape(b, *self.grid.shape)

    # ------------------------------------------------------------------ explicit matrix
    def to_sparse(self) -> scipy.sparse.csr_matrix:
        """The operator as an explicit ``(K*M, N^d)`` CSR matrix (float64) with the same weights."""
        rows, cols, vals = [], [], []
        idx = self.voxel_index.numpy()
        hv = self.grid.voxel_volume
        for k0, k1, s0, s1, w in self._chunks():
            c = np.tile(idx, k1 - k0)
            wn = w.numpy()
            rows += [s0.numpy(), s1.numpy()]
            cols += [c, c]
            vals += [(1 - wn) * hv, wn * hv]
        shape = (self.n_orientations * self.n_slabs, math.prod(self.grid.shape))
        mat = scipy.sparse.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape
        )
        return mat.tocsr()
