"""``rotate_sum``: the reference dip transform, rotation by ``grid_sample`` plus slab sums.

The paper's ``B = S R``: rotate the object into the frame of the orientation, then sum the
rotated volume plane by plane into slabs. The rotated frame is a grid like the object's (``N`` planes
of ``N x N`` (3D) or ``N`` (2D) samples, one voxel apart), aligned with ``theta``; each plane's sum
is shared between the slabs it overlaps (:func:`~dipnet.operators.splat.plane_slab_weights`).

The rotation moves each voxel's volume to the trilinear (bilinear) neighbours of its position
in the rotated frame: the exact transpose of sampling the rotated frame with ``grid_sample``
at the voxel centres. Pushing rather than pulling keeps Archimedes exact: every voxel's
volume lands in the profile in full, so each profile sums to the object's volume. The
adjoint is ``grid_sample`` itself; the forward is its transpose, computed by autograd.

This backend is literal and slow (``O(K N^d)`` trilinear splats into ``K`` rotated volumes);
:class:`~dipnet.operators.splat.SplatOperator` gives identical numbers much faster.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from dipnet.core.counts import whole_number
from dipnet.core.grid import Grid
from dipnet.operators.base import DipOperator
from dipnet.operators.splat import plane_slab_weights, planes_to_slabs, slabs_to_planes


def orthonormal_frame(directions: torch.Tensor) -> torch.Tensor:
    """Rotated frames whose last axis is ``theta``: ``(K, d)`` -> ``(K, d, d)``.

    Row ``i`` of ``frame[k]`` is the object-frame unit vector of rotated axis ``i``; rotated
    coordinates of a point ``x`` are ``frame[k] @ x``.
    """
    th = directions / directions.norm(dim=-1, keepdim=True)
    if th.shape[1] == 2:
        perp = torch.stack([-th[:, 1], th[:, 0]], dim=-1)
        return torch.stack([perp, th], dim=1)
    helper = torch.zeros_like(th)
    use_x = th[:, 0].abs() < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    a = helper - th * (helper * th).sum(-1, keepdim=True)
    a = a / a.norm(dim=-1, keepdim=True)
    b = torch.linalg.cross(th, a, dim=-1)
    return torch.stack([a, b, th], dim=1)


class _PushRotateSum(torch.autograd.Function):
    """Forward = transpose of grid_sample (push), backward = grid_sample (its adjoint)."""

    @staticmethod
    def forward(ctx, volume_pts: torch.Tensor, op: "RotateSumOperator") -> torch.Tensor:  # type: ignore[override]
        ctx.op = op
        with torch.enable_grad():
            return op._push(volume_pts.detach())

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        return ctx.op._pull(grad_out), None


class RotateSumOperator(DipOperator):
    """Reference dip transform: trilinear rotation with ``grid_sample``, then slab sums.

    Args:
        grid, directions, n_slabs: see :class:`~dipnet.operators.base.DipOperator`.
        chunk: orientations rotated at once (memory ``chunk * N^d`` floats).
    """

    def __init__(self, grid: Grid, directions: torch.Tensor, n_slabs: int | None = None, chunk: int = 8) -> None:
        super().__init__(grid, directions, n_slabs)
        self.register_buffer("slab_weights", plane_slab_weights(grid, self.n_slabs))
        self.chunk = whole_number("chunk (orientations rotated at once)", chunk, 1)  # 0, -1: obscure errors
        self.register_buffer("voxel_index", torch.nonzero(self.mask.reshape(-1)).squeeze(1))
        # grid_sample, align_corners=False: normalised coordinate = mm / (extent / 2) on every
        # rotated axis (the rotated grid has the same extent as the object grid).
        self.register_buffer("points", grid.centers().reshape(-1, grid.ndim)[self.voxel_index] / (grid.extent / 2))
        self.register_buffer("frames", orthonormal_frame(self.directions))

    def _sample_grid(self, k0: int, k1: int, dtype: torch.dtype) -> torch.Tensor:
        """Voxel centres in the rotated frames of orientations ``k0..k1``, as a ``grid_sample``
        grid ``(kc, 1, [1,] n_points, d)`` (built per chunk: memory ``O(chunk N^d)``)."""
        rotated = torch.einsum("kij,pj->kpi", self.frames[k0:k1], self.points).to(dtype)
        return rotated.reshape(k1 - k0, *([1] * (self.grid.ndim - 1)), -1, self.grid.ndim)

    def _rotated_shape(self) -> tuple[int, ...]:
        return (self.grid.n,) * self.grid.ndim

    def _pull(self, profiles: torch.Tensor) -> torch.Tensor:
        """Adjoint on the working voxels: ``(B, K, M)`` -> ``(B, n_points)``."""
        b = profiles.shape[0]
        out = profiles.new_zeros(b, self.voxel_index.numel())
        for k0 in range(0, self.n_orientations, self.chunk):
            k1 = min(k0 + self.chunk, self.n_orientations)
            planes = slabs_to_planes(profiles[:, k0:k1], self.slab_weights)  # (B, kc, N)
            rot = planes.transpose(0, 1).reshape(k1 - k0, b, -1, *([1] * (self.grid.ndim - 1)))
            rot = rot.expand(k1 - k0, b, *self._rotated_shape())
            g = self._sample_grid(k0, k1, profiles.dtype)
            sampled = F.grid_sample(rot, g, mode="bilinear", padding_mode="zeros", align_corners=False)
            out = out + sampled.reshape(k1 - k0, b, -1).sum(0)
        return out * self.grid.voxel_volume

    def _push(self, values: torch.Tensor) -> torch.Tensor:
        """Forward on the working voxels: ``(B, n_points)`` -> ``(B, K, M)``."""
        b = values.shape[0]
        out = []
        for k0 in range(0, self.n_orientations, self.chunk):
            k1 = min(k0 + self.chunk, self.n_orientations)
            rot = values.new_zeros(k1 - k0, b, *self._rotated_shape(), requires_grad=True)
            g = self._sample_grid(k0, k1, values.dtype)
            sampled = F.grid_sample(rot, g, mode="bilinear", padding_mode="zeros", align_corners=False)
            weights = values.unsqueeze(0).expand(k1 - k0, b, -1).reshape(sampled.shape)
            (rotated_volume,) = torch.autograd.grad(sampled, rot, grad_outputs=weights)
            plane_sums = rotated_volume.reshape(k1 - k0, b, self.grid.n, -1).sum(-1)
            out.append(planes_to_slabs(plane_sums.transpose(0, 1), self.slab_weights))
        return torch.cat(out, dim=1) * self.grid.voxel_volume

    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        pts = volume.reshape(volume.shape[0], -1)[:, self.voxel_index]
        return _PushRotateSum.apply(pts, self)

    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        b = profiles.shape[0]
        out = profiles.new_zeros(b, math.prod(self.grid.shape))
        out = out.index_copy(1, self.voxel_index, self._pull(profiles))
        return out.reshape(b, *self.grid.shape)
