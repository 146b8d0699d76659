"""Dipping orientations: unit vectors in the object frame.

A *dip direction* ``theta`` is the unit vector, expressed in the object's frame (the grid
frame, components ordered ``(x, y[, z])``), that points **up** in the tank, i.e. against the
direction of travel. The water line sits at height ``t = x . theta`` over the object, so the
parts with the smallest ``t`` go under water first and the dip profile is ordered by
increasing ``t``. Since a profile along ``-theta`` is the same profile reversed, a hemisphere
(``z >= 0`` in 3D, angles in ``[0, 180)`` degrees in 2D) holds every distinct orientation.
"""

from __future__ import annotations

import math

import numpy as np
import torch


def angles_2d(k: int, *, start_deg: float = 0.0) -> torch.Tensor:
    """``k`` equally spaced 2D angles in ``[0, 180)`` degrees, shape ``(k,)``, degrees."""
    _check_count(k)
    return start_deg + torch.arange(k, dtype=torch.float64) * (180.0 / k)


def directions_2d(angles_deg: torch.Tensor | np.ndarray | list[float]) -> torch.Tensor:
    """Unit vectors ``(cos a, sin a)`` for angles in degrees; shape ``(k, 2)``."""
    a = torch.deg2rad(torch.as_tensor(angles_deg, dtype=torch.float64))
    return torch.stack([torch.cos(a), torch.sin(a)], dim=-1)


def fibonacci_hemisphere(k: int) -> torch.Tensor:
    """``k`` nearly uniform directions on the upper hemisphere (Fibonacci lattice), ``(k, 3)``."""
    _check_count(k)
    i = torch.arange(k, dtype=torch.float64)
    z = 1.0 - (i + 0.5) / k  # uniform in (0, 1): equal-area bands of the hemisphere
    golden = math.pi * (3.0 - math.sqrt(5.0))
    phi = golden * i
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def random_hemisphere(k: int, seed: int) -> torch.Tensor:
    """``k`` directions uniform on the upper hemisphere from an explicit seed, ``(k, 3)``."""
    _check_count(k)
    gen = torch.Generator().manual_seed(int(seed))
    v = torch.randn(k, 3, generator=gen, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    return v * torch.where(v[:, 2:] < 0, -1.0, 1.0)


def paper_grid(n_theta: int, n_phi: int) -> torch.Tensor:
    """The paper's grid: polar ``theta`` in ``[0, 90)``, azimuth ``phi`` in ``[0, 360)``.

    Directions ``(sin t cos p, sin t sin p, cos t)``; shape ``(n_theta * n_phi, 3)``, theta-major.
    """
    _check_count(n_theta)
    _check_count(n_phi)
    t = torch.deg2rad(torch.arange(n_theta, dtype=torch.float64) * (90.0 / n_theta))
    p = torch.deg2rad(torch.arange(n_phi, dtype=torch.float64) * (360.0 / n_phi))
    tt, pp = torch.meshgrid(t, p, indexing="ij")
    v = torch.stack([tt.sin() * pp.cos(), tt.sin() * pp.sin(), tt.cos()], dim=-1)
    return v.reshape(-1, 3)


def rig_to_direction(tilt_deg, spin_deg) -> torch.Tensor:
    """Rig angles to dip directions in the object frame; shape ``(k, 3)``.

    The rig first *spins* the object by ``spin_deg`` about its own z axis (the axis that is
    vertical at rest), then *tilts* that axis by ``tilt_deg`` away from the vertical. The
    vertical "up" then lies at polar angle ``tilt`` from the object's z axis and at azimuth
    ``-spin`` about it: ``(sin(tilt) cos(spin), -sin(tilt) sin(spin), cos(tilt))``.
    This is the physically consistent reading of the authors' robot (R1 = tilt, R2 = spin).
    """
    t = torch.deg2rad(torch.as_tensor(tilt_deg, dtype=torch.float64)).reshape(-1)
    s = torch.deg2rad(torch.as_tensor(spin_deg, dtype=torch.float64)).reshape(-1)
    t, s = torch.broadcast_tensors(t, s)
    return torch.stack([t.sin() * s.cos(), -t.sin() * s.sin(), t.cos()], dim=-1)


def make_directions(kind: str, k: int, ndim: int, seed: int = 0) -> torch.Tensor:
    """Named orientation set: ``fibonacci`` | ``random`` | ``uniform`` (2D angles); ``(k, ndim)``."""
    if ndim == 2:
        if kind == "random":
            gen = torch.Generator().manual_seed(int(seed))
            return directions_2d(torch.rand(k, generator=gen, dtype=torch.float64) * 180.0)
        return directions_2d(angles_2d(k))
    if kind == "fibonacci" or kind == "uniform":
        return fibonacci_hemisphere(k)
    if kind == "random":
        return random_hemisphere(k, seed)
    raise ValueError(f"unknown orientation set {kind!r}; choose fibonacci, random or uniform")


def _check_count(k: int) -> None:
    if int(k) != k or k < 1:
        raise ValueError(f"number of orientations must be a positive integer, got {k!r}")
