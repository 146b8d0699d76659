"""Dip volume curves: exact (a mesh's plane sweep, against a cube) and tabulated (against the ball's closed form)."""

import math

import numpy as np
import pytest
import trimesh

from dipnet.shapes import Ball, from_trimesh
from dipnet.simulator.volume_curve import ExactCurve, TabulatedCurve, dip_volume_curve

R = 20.0
UP = np.array([0.0, 0.0, 1.0])
HEIGHTS = np.linspace(-R, R, 41)


def cap_volume(t):
    """Volume of a ball of radius R (centre at 0) below height t: pi h^2 (3R - h) / 3 with h = R + t."""
    h = np.clip(R + t, 0.0, 2 * R)
    return math.pi * h**2 * (3 * R - h) / 3


class NoSweep:
    """A ball seen only through ``volume_below`` (no plane sweep): the tabulated curve's case."""

    def __init__(self, ball):
        self.ball = ball

    def radius(self):
        return self.ball.radius()

    def volume_below(self, directions, heights):
        return self.ball.volume_below(directions, heights)


def test_a_mesh_gets_the_exact_curve_with_its_cross_section():
    a = 10.0  # a cube of side 2a: V(t) = 4 a^2 (t + a), dV/dt = 4 a^2 inside
    curve = dip_volume_curve(from_trimesh(trimesh.creation.box(extents=[2 * a] * 3), center=False), UP)
    assert isinstance(curve, ExactCurve) and curve.monotone and curve.max_area is None
    t = np.linspace(-a + 0.5, a - 0.5, 21)
    volume, area = curve.volume_and_area(t)
    assert np.allclose(volume, 4 * a**2 * (t + a), rtol=1e-9)
    assert np.allclose(area, 4 * a**2, rtol=1e-9)
    assert curve.total == pytest.approx(8 * a**3)


def test_a_shape_without_a_sweep_gets_an_exact_volume_and_a_tabulated_slope():
    curve = dip_volume_curve(NoSweep(Ball(R)), UP)
    assert isinstance(curve, TabulatedCurve)
    assert np.allclose(curve.volume(HEIGHTS), cap_volume(HEIGHTS), rtol=1e-9, atol=1e-6)
    inside = HEIGHTS[np.abs(HEIGHTS) < R - 1]
    _, area = curve.volume_and_area(inside)
    assert np.allclose(area, math.pi * (R**2 - inside**2), rtol=2e-3)
    assert curve.max_area == pytest.approx(math.pi * R**2, rel=1e-3)
    assert curve.total == pytest.approx(4 / 3 * math.pi * R**3, rel=1e-9)
