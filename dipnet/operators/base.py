"""The DipOperator interface shared by every backend.

Discretisation contract
-----------------------
For orientation ``k`` (unit "up" vector ``theta_k`` in the object frame, see
:mod:`dipnet.core.orientations`) the profile has ``M`` slabs of equal thickness
``delta = extent / M`` covering heights ``t`` in ``[-extent/2, extent/2]`` (slab ``j`` spans
``[-extent/2 + j delta, -extent/2 + (j+1) delta)``, ordered by increasing ``t``, i.e. in the
order in which they go under water). Voxel ``v`` with occupancy ``f_v`` in ``[0, 1]`` and
centre ``x_v`` contributes the volume ``f_v * voxel_volume`` to the slabs around its height
``t_v = x_v . theta_k``. Only voxels inside the working ball (:meth:`Grid.working_mask`)
count, so every profile of a volume sums exactly to its (masked) occupancy volume.

Units: volumes hold occupancy fractions (dimensionless); profiles hold slab volumes in mm^3
(mm^2 in 2D). Shapes: volumes ``(*grid.shape)`` or ``(B, *grid.shape)``; profiles ``(K, M)``
or ``(B, K, M)``.

Inputs: :meth:`DipOperator.forward` and :meth:`DipOperator.adjoint` take anything
``torch.as_tensor`` takes (a tensor, a numpy array), as the constructor does for the directions,
and return a tensor. A floating tensor is used as it is (its dtype, device and autograd graph
kept); a bool or integer one (e.g. ``Reconstruction.binary``) is an occupancy (``True`` = 1) and
is converted to the operator's float dtype (that of its ``directions`` buffer, float64 unless
the module was cast). Complex inputs are refused with a ``TypeError``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import nn

from dipnet.core.grid import Grid, as_grid, slab_count
from dipnet.core.orientations import unit_directions


class DipOperator(nn.Module, ABC):
    """Linear dip transform ``A``: occupancy volume -> slab volumes, with its exact adjoint.

    Args:
        grid: the voxel grid.
        directions: unit dip directions, shape ``(K, grid.ndim)``, components ``(x, y[, z])``.
        n_slabs: slabs per profile ``M`` (default ``grid.n``).
    """

    def __init__(self, grid: Grid, directions: torch.Tensor, n_slabs: int | None = None) -> None:
        super().__init__()
        grid = as_grid(grid)
        directions = unit_directions(directions, grid.ndim)
        n_slabs = slab_count(grid, n_slabs)
        self.grid = grid
        self.n_slabs = n_slabs
        self.register_buffer("directions", directions)
        self.register_buffer("mask", grid.working_mask())

    # ----------------------------------------------------------------- geometry
    @property
    def n_orientations(self) -> int:
        """Number of orientations ``K``."""
        return int(self.directions.shape[0])

    @property
    def slab_thickness(self) -> float:
        """Slab thickness ``delta`` in mm."""
        return self.grid.extent / self.n_slabs

    @property
    def profile_shape(self) -> tuple[int, int]:
        """``(K, M)``."""
        return (self.n_orientations, self.n_slabs)

    def slab_edges(self) -> torch.Tensor:
        """Slab boundaries along ``t`` in mm, shape ``(M + 1,)``."""
        return torch.linspace(-self.grid.extent / 2, self.grid.extent / 2, self.n_slabs + 1, dtype=torch.float64)

    # ----------------------------------------------------------------- application
    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """Slab volumes (mm^3) of ``volume``: ``(*shape)`` -> ``(K, M)``, ``(B, *shape)`` -> ``(B, K, M)``.

        ``volume`` holds occupancy fractions; bool, integer and numpy inputs are accepted (module docstring)."""
        volume = self._as_real_tensor(volume, "volume")
        batched = self._check_volume(volume)
        v = volume if batched else volume.unsqueeze(0)
        out = self._forward(v.masked_fill(~self.mask, 0.0))  # not v * mask: a NaN or inf outside is no 0
        return out if batched else out.squeeze(0)

    def adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        """Exact transpose of :meth:`forward`: ``(K, M)`` -> ``(*shape)``, ``(B, K, M)`` -> ``(B, *shape)``.

        ``profiles`` holds slab volumes in mm^3; integer and numpy inputs are accepted (module docstring)."""
        profiles = self._as_real_tensor(profiles, "profiles")
        if profiles.shape[-2:] != self.profile_shape or profiles.ndim not in (2, 3):
            raise ValueError(f"profiles must have shape (K, M) = {self.profile_shape} (optionally batched), "
                             f"got {tuple(profiles.shape)}")
        batched = profiles.ndim == 3
        p = profiles if batched else profiles.unsqueeze(0)
        out = self._adjoint(p) * self.mask.to(p.dtype)
        return out if batched else out.squeeze(0)

    def cumulative(self, volume: torch.Tensor) -> torch.Tensor:
        """Submerged volume (mm^3) once slabs ``0..j`` are under water, same shape as :meth:`forward`."""
        return torch.cumsum(self.forward(volume), dim=-1)

    @abstractmethod
    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        """``(B, *shape)`` (already masked) -> ``(B, K, M)``."""

    @abstractmethod
    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        """``(B, K, M)`` -> ``(B, *shape)`` (masked by the caller)."""

    # ----------------------------------------------------------------- linear algebra views
    def as_linear_operator(self) -> scipy.sparse.linalg.LinearOperator:
        """Matrix-free scipy view on flattened float64 arrays: ``(K*M, N^d)``."""
        shape = (self.n_orientations * self.n_slabs, math.prod(self.grid.shape))

        def matvec(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                vol = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64)).reshape(self.grid.shape)
                return self.forward(vol).reshape(-1).numpy()

        def rmatvec(y: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                prof = torch.from_numpy(np.ascontiguousarray(y, dtype=np.float64)).reshape(self.profile_shape)
                return self.adjoint(prof).reshape(-1).numpy()

        return scipy.sparse.linalg.LinearOperator(shape, matvec=matvec, rmatvec=rmatvec, dtype=np.float64)

    def _as_real_tensor(self, values: torch.Tensor | np.ndarray, name: str) -> torch.Tensor:
        """``values`` as a real floating tensor: floating tensors unchanged (autograd kept), numpy
        arrays via ``torch.as_tensor`` on the operator's device, bool / integer values converted
        to the operator's float dtype. ``float16`` raises a ``TypeError``: its largest value, 65504, is below the
        slab volumes of objects a few centimetres across (mm^3), so profiles came back ``inf``."""
        if not isinstance(values, torch.Tensor):  # a view with negative strides (np.flip) is copied: torch takes none
            values = torch.as_tensor(np.ascontiguousarray(values), device=self.directions.device)
        if values.is_complex():
            raise TypeError(f"{name} must be real (occupancies or slab volumes), got dtype {values.dtype}")
        if values.dtype == torch.float16:
            raise TypeError(f"{name} in float16 cannot hold slab volumes (mm^3; its largest value is 65504): give it "
                            "as float32 or float64 (.float())")
        if not values.is_floating_point():
            values = values.to(self.directions.dtype)
        return values

    def _check_volume(self, volume: torch.Tensor) -> bool:
        shape = self.grid.shape
        if tuple(volume.shape) == shape:
            return False
        if volume.ndim == len(shape) + 1 and tuple(volume.shape[1:]) == shape:
            return True
        raise ValueError(f"volume must have shape {shape} or (B, *{shape}), got {tuple(volume.shape)}")
