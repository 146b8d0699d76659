"""The divergence-theorem dips (volume below a plane) against independent closed forms."""

import itertools
import math

import numpy as np
import pytest
import torch
import trimesh

from dipnet.shapes import Ball, Box, boundary_volume_below


def unit_directions(k: int, d: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(k, d))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def ball_below(r: float, h: np.ndarray) -> np.ndarray:
    t = np.clip(h, -r, r)
    return np.pi * (r**2 * (t + r) - (t**3 + r**3) / 3)


def test_ball_closed_form_matches_slab_integral():
    r, h = 2.0, np.linspace(-3, 3, 61)
    d = unit_directions(4, 3, 0)
    v = Ball(r, center=(0.3, -0.2, 0.1)).volume_below(torch.from_numpy(d), torch.from_numpy(h))
    assert v.shape == (4, 61) and v.dtype == torch.float64
    shift = d @ np.array([0.3, -0.2, 0.1])
    expect = ball_below(r, h[None, :] - shift[:, None])
    np.testing.assert_allclose(v.numpy(), expect, atol=1e-12)


def test_icosphere_mesh_formula_converges_to_ball():
    r, h = 1.0, np.linspace(-1.1, 1.1, 45)
    d = unit_directions(6, 3, 1)
    errors = []
    for sub in (1, 2, 3, 4):
        m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
        v = boundary_volume_below(m.vertices[m.faces], d, h)
        np.testing.assert_allclose(v[:, -1], m.volume, rtol=1e-12)  # closed mesh: top = volume
        errors.append(np.abs(v - ball_below(r, h)).max() / (4 / 3 * np.pi * r**3))
    assert errors[-1] < 3e-3
    assert all(b < 0.35 * a for a, b in zip(errors, errors[1:]))  # ~ 4x per subdivision


@pytest.mark.parametrize("ndim", [2, 3])
def test_box_matches_inclusion_exclusion(ndim):
    """Box below a tilted plane = sum over corners of +-(h - c.|theta|)_+^d / (d! prod|theta|)."""
    half = np.array([1.0, 0.6, 0.3])[:ndim]
    centre = np.array([0.2, -0.1, 0.05])[:ndim]
    box = Box(half, centre)
    h = np.linspace(-1.5, 1.5, 77)
    d = unit_directions(8, ndim, 2)
    v = box.volume_below(torch.from_numpy(d), torch.from_numpy(h)).numpy()
    for k, theta in enumerate(d):
        a = np.abs(theta)
        lo, hi = centre - half, centre + half
        lo_f = np.where(theta < 0, -hi, lo)
        hi_f = np.where(theta < 0, -lo, hi)
        ref = np.zeros_like(h)
        for corner in itertools.product((0, 1), repeat=ndim):
            c = np.where(np.array(corner) == 1, hi_f, lo_f)
            ref += (-1) ** sum(corner) * np.maximum(h - c @ a, 0) ** ndim
        ref /= math.factorial(ndim) * np.prod(a)
        np.testing.assert_allclose(v[k], ref, atol=1e-9 * box.volume)
    assert box.volume == pytest.approx(np.prod(2 * half))


def clipped_polygon_area(poly: np.ndarray, theta: np.ndarray, h: float) -> float:
    """Area of a simple polygon below x.theta < h by Sutherland-Hodgman clipping + shoelace."""
    out = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        fp, fq = p @ theta - h, q @ theta - h
        if fp <= 0:
            out.append(p)
        if (fp < 0) != (fq < 0) and fp != fq:
            out.append(p + (q - p) * fp / (fp - fq))
    if len(out) < 3:
        return 0.0
    x, y = np.array(out).T
    return 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_segments_match_polygon_clipping():
    """2D: exact area below a line for a random convex polygon (clipping keeps it convex)."""
    rng = np.random.default_rng(3)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 12))
    poly = np.stack([np.cos(angles), np.sin(angles)], 1) * rng.uniform(0.5, 1.5)
    segments = np.stack([poly, np.roll(poly, -1, axis=0)], axis=1)
    d = unit_directions(5, 2, 4)
    h = np.linspace(-1.6, 1.6, 33)
    v = boundary_volume_below(segments, d, h)
    ref = np.array([[clipped_polygon_area(poly, t, hh) for hh in h] for t in d])
    np.testing.assert_allclose(v, ref, atol=1e-12)


def test_heights_in_any_order_and_degenerate_directions():
    """Unsorted heights and planes parallel to faces (ties in vertex heights) are handled."""
    box = Box([1.0, 1.0, 1.0])
    h = np.array([0.5, -2.0, 1.0, -1.0, 0.0, 2.0])
    v = box.volume_below(torch.tensor([[0.0, 0.0, 1.0]]), torch.from_numpy(h)).numpy()[0]
    np.testing.assert_allclose(v, 4 * (np.clip(h, -1, 1) + 1), atol=1e-12)


def test_rejects_bad_arguments():
    ball = Ball(1.0)
    with pytest.raises(ValueError, match="unit"):
        ball.volume_below(torch.tensor([[0.0, 0.0, 2.0]]), torch.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        ball.volume_below(torch.tensor([[0.0, 1.0]]), torch.zeros(3))
