"""Exact dip profiles of simple solids, shared by test folders (on ``sys.path`` through ``tests/conftest.py``)."""

from __future__ import annotations

import math

import numpy as np
import torch

from dipnet.core.measurement import DipMeasurement


def ball_measurement(centre, radius: float, directions, h: float = 1.0, half_span: float = 60.0) -> DipMeasurement:
    """Exact slab volumes of a ball (mm^3) along ``directions`` ``(K, 3)``: ``pi (r^2 t - t^3 / 3)`` between the slab
    bounds (``h`` mm apart, from ``-half_span`` mm), ``t`` from the ball's centre, whose height along a direction is
    ``centre . theta``."""
    directions = np.asarray(directions, dtype=np.float64)
    edges = np.arange(-half_span, half_span + h / 2, h)

    def below(t):
        t = np.clip(t, -radius, radius)
        return math.pi * (radius**2 * t - t**3 / 3) + 2 * math.pi * radius**3 / 3

    profiles = np.stack([np.diff(below(edges - float(np.dot(centre, d)))) for d in directions])
    return DipMeasurement(torch.from_numpy(directions), torch.from_numpy(profiles), h,
                          torch.full((len(directions),), edges[0], dtype=torch.float64))
