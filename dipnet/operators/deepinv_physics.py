"""The dip operator as a ``deepinv`` linear physics, so the field's algorithms run on dips.

:func:`dip_physics` wraps a :class:`~dipnet.operators.base.DipOperator` ``A`` in a
``deepinv.physics.LinearPhysics`` whose ``A`` and ``A_adjoint`` are the operator's exact forward
and adjoint (:func:`deepinv_maps`, no autograd adjoint), in deepinv's layout: volumes ``x`` of
shape ``(B, 1, N, N, N)`` (``(B, 1, N, N)`` in 2D, occupancy fractions), measurements ``y`` of shape
``(B, 1, K, M)`` (slab volumes in mm^3). deepinv's solvers (``A_dagger``, ``prox_l2``, PnP / RED
iterations, its ``adjointness_test``) then work on dip data.

deepinv is an optional dependency: ``pip install "dipnet[learned]"`` (it imports torchvision, whose
build must match the installed torch).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from dipnet.core.optional import optional_import
from dipnet.operators.base import DipOperator

Map = Callable[..., torch.Tensor]


def deepinv_maps(operator: DipOperator) -> tuple[Map, Map]:
    """``(A, A_adjoint)`` of ``operator`` in deepinv's layout (see the module docstring); each
    accepts and ignores deepinv's keyword arguments and returns the input's dtype."""
    volume_shape = tuple(operator.grid.shape)

    def forward(x: torch.Tensor, **_) -> torch.Tensor:
        if x.ndim != len(volume_shape) + 2 or x.shape[1] != 1 or tuple(x.shape[2:]) != volume_shape:
            raise ValueError(f"deepinv volumes must have shape (B, 1, *{volume_shape}), got {tuple(x.shape)}")
        return operator(x[:, 0].to(operator.directions.dtype)).to(x.dtype)[:, None]

    def adjoint(y: torch.Tensor, **_) -> torch.Tensor:
        if y.ndim != 4 or y.shape[1] != 1 or tuple(y.shape[2:]) != operator.profile_shape:
            raise ValueError(f"deepinv measurements must have shape (B, 1, *{operator.profile_shape}), "
                             f"got {tuple(y.shape)}")
        return operator.adjoint(y[:, 0].to(operator.directions.dtype)).to(y.dtype)[:, None]

    return forward, adjoint


def dip_physics(operator: DipOperator, noise_sigma: float | None = None, **options):
    """``deepinv.physics.LinearPhysics`` of ``operator`` (see the module docstring).

    Args:
        operator: the dip operator.
        noise_sigma: white Gaussian noise (mm^3 per slab) of ``physics(x)``; ``None``: noise-free.
        **options: further ``LinearPhysics`` options (``max_iter``, ``tol``, ``solver``, ...).

    Raises:
        MissingExtraError: deepinv is not installed (or cannot be imported).
    """
    dinv = optional_import("deepinv", "learned", "the dip operator as a deepinv physics")
    forward, adjoint = deepinv_maps(operator)
    noise = dinv.physics.ZeroNoise() if noise_sigma is None else dinv.physics.GaussianNoise(sigma=float(noise_sigma))
    return dinv.physics.LinearPhysics(A=forward, A_adjoint=adjoint, img_size=(1, *operator.grid.shape),
                                      noise_model=noise, **options)
