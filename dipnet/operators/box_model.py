"""Exact slab volumes of the box-voxel model, by direct summation (a slow reference).

Voxel ``v`` is a box of side ``h`` with uniform density ``f_v``; its height along ``theta`` is
``t_v + theta . u`` with ``u`` uniform in ``[-h/2, h/2]^d``, whose distribution function is the
piecewise polynomial (sum of ``d`` uniforms of widths ``a_i = h |theta_i|``)

    C(s) = sum_{e in {0,1}^d} (-1)^|e| (s + sum(a)/2 - e . a)_+^d / (d! prod a_i).

Slab ``j`` receives ``f_v h^d (C(b_{j+1} - t_v) - C(b_j - t_v))``. Components with
``a_i < 1e-5 h`` are dropped (a negligible width, avoids cancellation). Cost
``O(K N^d 2^d)``: for tests and benchmarks of the
:class:`~dipnet.operators.fourier.FourierOperator`, which approximates this model.
"""

from __future__ import annotations

import itertools
import math

import torch

from dipnet.core.grid import Grid

_CHUNK = 1 << 22  # voxel x edge pairs per step


def _box_cdf(s: torch.Tensor, widths: list[float]) -> torch.Tensor:
    """Distribution function of a sum of centred uniforms of the given widths at ``s``."""
    total = sum(widths) / 2
    deg = len(widths)
    out = torch.zeros_like(s)
    for signs in itertools.product((0, 1), repeat=deg):
        shift = total - sum(e * a for e, a in zip(signs, widths))
        out += (-1) ** sum(signs) * (s + shift).clamp(min=0) ** deg
    return out / (math.factorial(deg) * math.prod(widths))


def box_voxel_profiles(grid: Grid, directions: torch.Tensor, n_slabs: int, volume: torch.Tensor) -> torch.Tensor:
    """Slab volumes (mm^3, float64) of the box-voxel model of ``volume`` ``(*shape)``: ``(K, M)``.

    Only voxels in the working ball count, as in every operator backend.
    """
    directions = torch.as_tensor(directions, dtype=torch.float64)
    directions = directions / directions.norm(dim=1, keepdim=True)
    mask = grid.working_mask().reshape(-1)
    pts = grid.centers().reshape(-1, grid.ndim)[mask]
    vals = volume.detach().to(torch.float64).reshape(-1)[mask] * grid.voxel_volume
    edges = torch.linspace(-grid.extent / 2, grid.extent / 2, n_slabs + 1, dtype=torch.float64)
    out = torch.zeros(directions.shape[0], n_slabs, dtype=torch.float64)
    step = max(1, _CHUNK // (n_slabs + 1))
    for k, theta in enumerate(directions):
        widths = [grid.voxel_size * float(a) for a in theta.abs() if a > 1e-5]
        for p0 in range(0, pts.shape[0], step):
            t = pts[p0:p0 + step] @ theta
            cdf = _box_cdf(edges[None, :] - t[:, None], widths)  # (chunk, M + 1)
            out[k] += vals[p0:p0 + step] @ (cdf[:, 1:] - cdf[:, :-1])
    return out
