"""``splat``: the dip transform by direct splatting, with no rotated volume.

Each voxel's volume is shared linearly (a hat kernel) between the two sampling planes
nearest to its height ``t_v = x_v . theta``. The ``N`` planes lie one voxel apart at the heights of
the voxel layers' centres, and plane ``i`` stands for the layer ``[c_i - h/2, c_i + h/2]`` (``h`` the
voxel size), which :func:`plane_slab_weights` shares between the slabs by overlap. So a dip along a
grid axis is exact for any number of slabs (each voxel layer lands in the slabs it overlaps), and with
``M = N`` slabs (or ``N`` a multiple of ``M``) each plane lies in one slab. This is exactly what
:class:`~dipnet.operators.rotate_sum.RotateSumOperator` computes (rotation by trilinear interpolation
followed by plane sums), because the in-plane interpolation weights of a voxel sum to one: only the
height matters. Cost ``O(K N^d)`` with no ``N^d``-sized temporaries per orientation, and the explicit
sparse matrix comes from the same weights.
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


def plane_slab_weights(grid: Grid, n_slabs: int) -> torch.Tensor | None:
    """Share of sampling plane ``i`` (the layer ``[c_i - h/2, c_i + h/2]`` of the ``N`` voxel layers along the
    dip, ``h`` the voxel size in mm) in slab ``j``: the overlap over ``h``, ``(N, M)`` float64, rows summing
    to 1. ``None`` when planes and slabs coincide (``M = N``)."""
    if n_slabs == grid.n:
        return None
    layers = torch.linspace(-grid.extent / 2, grid.extent / 2, grid.n + 1, dtype=torch.float64)
    slabs = torch.linspace(-grid.extent / 2, grid.extent / 2, n_slabs + 1, dtype=torch.float64)
    overlap = (torch.minimum(layers[1:, None], slabs[None, 1:]) - torch.maximum(layers[:-1, None], slabs[None, :-1]))
    return overlap.clamp(min=0.0) / grid.voxel_size


def planes_to_slabs(planes: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """Plane volumes ``(..., N)`` -> slab volumes ``(..., M)`` by :func:`plane_slab_weights` ``weights``."""
    return planes if weights is None else planes @ weights.to(planes.dtype)


def slabs_to_planes(profiles: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """The adjoint of :func:`planes_to_slabs`: ``(..., M)`` -> ``(..., N)``."""
    return profiles if weights is None else profiles @ weights.to(profiles.dtype).T


class SplatOperator(DipOperator):
    """Dip transform by linear splatting of voxel heights into slabs (see module docstring)."""

    def __init__(self, grid: Grid, directions: torch.Tensor, n_slabs: int | None = None) -> None:
        super().__init__(grid, directions, n_slabs)
        self.register_buffer("slab_weights", plane_slab_weights(grid, self.n_slabs))
        self.register_buffer("voxel_index", torch.nonzero(self.mask.reshape(-1)).squeeze(1))
        self.register_buffer("points", grid.centers().reshape(-1, grid.ndim)[self.voxel_index])
        n_pts = self.points.shape[0]
        self._chunk = max(1, _CHUNK_ELEMENTS // n_pts)
        self._cache: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
        self._use_cache = n_pts * self.n_orientations * 24 <= _CACHE_BYTES

    # ------------------------------------------------------------------ weights
    def _chunks(self):
        """Yield ``(k0, k1, plane0, plane1, w)``: flat (k, plane) indices (``N`` planes per orientation) of the
        lower / upper plane and the upper weight, each of shape ``(n_points * (k1 - k0),)``, orientation-major."""
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
        n = self.grid.n
        t = self.directions[k0:k1] @ self.points.T  # (kc, n_points), mm
        u = (t + self.grid.extent / 2) / self.grid.voxel_size - 0.5  # plane coordinate
        i0 = torch.floor(u).clamp(0, n - 2)
        w = (u - i0).clamp(0.0, 1.0)
        p0 = (torch.arange(k0, k1) * n).unsqueeze(1) + i0.long()
        return p0.reshape(-1), (p0 + 1).reshape(-1), w.reshape(-1)

    # ------------------------------------------------------------------ application
    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        b = volume.shape[0]
        f = volume.reshape(b, -1)[:, self.voxel_index] * self.grid.voxel_volume  # (B, n_points)
        out = volume.new_zeros(b, self.n_orientations * self.grid.n)
        for k0, k1, s0, s1, w in self._chunks():
            w = w.to(volume.dtype)
            src = f.repeat(1, k1 - k0)  # orientation-major, matches the weight layout
            out = out.index_add(1, s0, src * (1 - w)).index_add(1, s1, src * w)
        return planes_to_slabs(out.reshape(b, self.n_orientations, self.grid.n), self.slab_weights)

    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        b = profiles.shape[0]
        y = slabs_to_planes(profiles, self.slab_weights).reshape(b, -1)
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
        shape = (self.n_orientations * self.grid.n, math.prod(self.grid.shape))
        mat = scipy.sparse.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape
        ).tocsr()
        if self.slab_weights is None:
            return mat
        binning = scipy.sparse.csr_matrix(self.slab_weights.T.numpy())  # (M, N)
        return (scipy.sparse.kron(scipy.sparse.eye(self.n_orientations, format="csr"), binning) @ mat).tocsr()
