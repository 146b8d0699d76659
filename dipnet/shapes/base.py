"""The protocol every dipnet shape (2D or 3D) satisfies, and its shared occupancy sampler.

A shape lives in the grid frame: millimetres, already positioned (usually centred on the
origin). It answers three questions:

* ``occupancy(grid, supersample)``: the fraction of every voxel it fills (the *truth* volume);
* ``volume_below(directions, heights)``: the exact volume of the part with ``x . theta < h``,
  i.e. the submerged volume when the water line is at height ``h`` along the "up" vector
  ``theta``. It comes from the true geometry, never from a voxel grid, so that simulated data
  is not made with the reconstruction's own discretisation (no "inverse crime");
* ``volume``: the volume of what displaces water (mm^3, an area in mm^2 in 2D).

Physics: water reaches every cavity open to the outside, never a sealed one; ``occupancy`` and
``volume_below`` of every shape follow that (a sealed void counts as solid).
"""

from __future__ import annotations

import itertools
import warnings
from abc import ABC, abstractmethod

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.grid import Grid, as_grid


class ShapeError(ValueError):
    """A shape cannot be made (missing / unreadable / empty mesh file, no enclosed volume, ...)."""


class ShapeWarning(UserWarning):
    """A shape was repaired or changed on load (holes filled, sealed voids filled, ...)."""


class Shape(ABC):
    """A solid in the grid frame (mm).

    Attributes:
        name: a short label.
        ndim: 2 or 3.
        volume: exact volume (mm^3; area in mm^2 in 2D) of what displaces water.
        notes: human-readable notes on what was changed when the shape was made.
    """

    name: str
    ndim: int
    volume: float
    notes: list[str]

    @abstractmethod
    def contains(self, points: np.ndarray) -> np.ndarray:
        """Inside test: ``points`` (P, ndim) float64 mm -> (P,) bool."""

    @abstractmethod
    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """Exact volume of the part with ``x . theta < h``.

        Args:
            directions: (K, ndim) unit "up" vectors ``theta``.
            heights: (H,) water-line heights ``h`` in mm (object frame).

        Returns:
            (K, H) float64 tensor in mm^3 (mm^2 in 2D).
        """

    @abstractmethod
    def radius(self) -> float:
        """Largest distance (mm) of the shape from the origin."""

    def dip_bytes_per_reading(self) -> float:
        """Peak memory (bytes) per reading while one dip of this shape is simulated: the dip
        solver's arrays over the readings (stage, rise, volume, slope, brackets, sort orders).
        Measured: a ball 315, the chamber box 1,332 bytes per reading (400,000-reading dips)."""
        return 1500.0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo, hi)``, each (ndim,) mm; no point outside is inside."""
        r = self.radius()
        return np.full(self.ndim, -r), np.full(self.ndim, r)

    def occupancy(self, grid: Grid, supersample: int = 1) -> torch.Tensor:
        """Fraction of each voxel inside the shape.

        Args:
            grid: a grid with ``grid.ndim == self.ndim``.
            supersample: ``s``; each voxel is sampled at ``s^ndim`` evenly spaced sub-voxel points
                and the fraction inside is returned (partial volume). ``s = 1`` tests the centres.

        Returns:
            float32 tensor of shape ``grid.shape`` with values in [0, 1].
        """
        if as_grid(grid).ndim != self.ndim:
            raise ShapeError(f"shape {self.name!r} is {self.ndim}D but the grid is {grid.ndim}D")
        s = check_supersample(supersample)
        h = grid.voxel_size
        centres = grid.centers().numpy().reshape(-1, self.ndim)
        lo, hi = self.bounds()
        total = np.zeros(len(centres))
        for sub in itertools.product(range(s), repeat=self.ndim):
            offset = ((np.asarray(sub) + 0.5) / s - 0.5) * h
            pts = centres + offset
            near = np.all((pts >= lo) & (pts <= hi), axis=1)
            if near.any():
                total[near] += self.contains(pts[near])
        occ = (total / s**self.ndim).reshape(grid.shape)
        return torch.from_numpy(occ).to(torch.float32)

    def _warn(self, message: str) -> None:
        """Record ``message`` in ``notes`` and emit it as a :class:`ShapeWarning`."""
        self.notes.append(message)
        warnings.warn(message, ShapeWarning, stacklevel=3)


def check_radius(radius: float, what: str = "shape radius") -> float:
    """``radius`` (mm) as a ``float`` after refusing, with a :class:`ShapeError` naming ``what``, anything but a
    finite, positive real number: text, null and a boolean are refused, not compared (``shape.radius=abc`` failed
    as a ``TypeError`` naming no option)."""
    if not (is_real(radius) and 0 < radius < np.inf):  # NaN fails too
        raise ShapeError(f"{what} must be a finite, positive number (mm), got {radius!r}")
    return float(radius)


def check_supersample(supersample: int) -> int:
    """``supersample`` as an ``int`` after refusing, with a ``ValueError`` naming it, anything but a whole number
    >= 1: every shape's :meth:`Shape.occupancy` checks it, those that answer exactly without sampling too (a box
    took 0 or -1 without a word).

    Args:
        supersample: sub-voxel points per axis, as given to :meth:`Shape.occupancy`.
    """
    if not (is_real(supersample) and np.isfinite(supersample) and supersample >= 1
            and int(supersample) == supersample):
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    return int(supersample)


def check_dips(
    directions: torch.Tensor | np.ndarray, heights: torch.Tensor | np.ndarray, ndim: int
) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``volume_below`` arguments and return them as float64 numpy arrays.

    Args:
        directions: (K, ndim) unit vectors.
        heights: (H,) mm.

    Returns:
        ``(directions (K, ndim), heights (H,))`` float64.
    """
    d = torch.as_tensor(directions).detach().cpu().to(torch.float64).numpy()
    t = torch.as_tensor(heights).detach().cpu().to(torch.float64).numpy()
    if d.ndim != 2 or d.shape[1] != ndim:
        raise ValueError(f"directions must have shape (K, {ndim}), got {tuple(d.shape)}")
    if t.ndim != 1:
        raise ValueError(f"heights must have shape (H,), got {tuple(t.shape)}")
    norms = np.linalg.norm(d, axis=1)
    if not np.allclose(norms, 1.0, atol=1e-6):
        raise ValueError("directions must be unit vectors")
    return d, t
