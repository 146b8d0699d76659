"""The submerged volume ``V(t)`` of a shape along one direction, and its slope, for the dip solver.

:func:`dip_volume_curve` returns the fastest exact curve a shape offers:

* shapes with a ``plane_sweep(directions)`` method (triangle meshes) give an
  :class:`ExactCurve`: ``V`` and the cross-section ``a = dV/dt`` both in closed form from one
  :class:`~dipnet.shapes.divergence.PlaneSweep` (the simplices sorted once per direction);
* any other shape gives a :class:`TabulatedCurve`: exact ``V`` from ``volume_below`` and the
  slope from a fine table of ``V`` (finite differences).

Either way ``V`` is exact; the slope only steers Newton's method, so its accuracy sets the
speed of convergence, not the answer.
"""

from __future__ import annotations

import numpy as np
import torch

_TABLE_POINTS = 4097  # heights of the slope table of shapes without a plane sweep


class ExactCurve:
    """``V`` and ``a = dV/dt`` of a shape with a plane sweep, along one direction.

    Args:
        shape: a shape with ``plane_sweep(directions (1, d)) -> PlaneSweep`` and ``radius()``.
        direction: unit "up" vector ``(d,)``.

    Attributes:
        total: the volume below the top of the bounding sphere, mm^3.
        monotone: whether ``V`` rises monotonically (a closed surface); an open one's flux need not.
        max_area: ``None``: the cross-section is exact wherever it is evaluated, so the dip
            solver checks it there instead of on a table.
    """

    max_area = None

    def __init__(self, shape, direction: np.ndarray) -> None:
        self._sweep = shape.plane_sweep(np.asarray(direction, dtype=np.float64).reshape(1, -1))
        self.total = float(self.volume(np.array([float(shape.radius())]))[0])
        self.monotone = self._sweep.closed()[0]

    def volume(self, t: np.ndarray) -> np.ndarray:
        """``V(t)`` for heights ``t`` (n,) mm -> (n,) mm^3."""
        return self.volume_and_area(t)[0]

    def volume_and_area(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``V(t)`` (n,) mm^3 and the cross-section ``dV/dt`` (n,) mm^2 at heights ``t`` (n,) mm."""
        volume, area = self._sweep.volume_and_area(np.asarray(t, dtype=np.float64)[None])
        return volume[0], area[0]


class TabulatedCurve:
    """Exact ``V`` from ``shape.volume_below``; the slope from a table of ``_TABLE_POINTS`` heights.

    Every such shape is a solid, so ``V`` is taken as monotone.

    Args:
        shape: any :class:`~dipnet.shapes.Shape`.
        direction: unit "up" vector ``(d,)``.
    """

    def __init__(self, shape, direction: np.ndarray) -> None:
        self._shape = shape
        self.monotone = True
        self._theta = torch.as_tensor(np.asarray(direction, dtype=np.float64)).reshape(1, -1)
        r = float(shape.radius())
        self._t = np.linspace(-r, r, _TABLE_POINTS)
        table = np.maximum.accumulate(np.maximum(self.volume(self._t), 0.0))
        self._slope = np.diff(table) / np.diff(self._t)  # mm^2
        self._mid = 0.5 * (self._t[1:] + self._t[:-1])
        self.total = float(table[-1])
        self.max_area = float(self._slope.max())  # mm^2, largest cross-section on the table

    def volume(self, t: np.ndarray) -> np.ndarray:
        """``V(t)`` for heights ``t`` (n,) mm -> (n,) mm^3 (exact)."""
        heights = torch.from_numpy(np.ascontiguousarray(t, dtype=np.float64))
        return self._shape.volume_below(self._theta, heights)[0].detach().cpu().numpy().astype(np.float64)

    def volume_and_area(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact ``V(t)`` (n,) mm^3 and the table's cross-section at ``t`` (n,) mm^2."""
        return self.volume(t), np.interp(t, self._mid, self._slope, left=0.0, right=0.0)


def dip_volume_curve(shape, direction: np.ndarray) -> ExactCurve | TabulatedCurve:
    """The exact curve of ``shape`` along ``direction`` (closed-form slope when available)."""
    if hasattr(shape, "plane_sweep"):
        return ExactCurve(shape, direction)
    return TabulatedCurve(shape, direction)
