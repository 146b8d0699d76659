import math

import pytest
import torch

from dipnet.core import orientations as o


def test_fibonacci_hemisphere_is_unit_upper_and_uniform():
    v = o.fibonacci_hemisphere(400)
    assert v.shape == (400, 3)
    assert torch.allclose(v.norm(dim=1), torch.ones(400, dtype=torch.float64))
    assert bool((v[:, 2] > 0).all())
    # equal-area: the fraction of points above height z is 1 - z, and azimuths are balanced
    for z in (0.25, 0.5, 0.75):
        assert abs((v[:, 2] > z).double().mean().item() - (1 - z)) < 0.01
    assert v[:, :2].mean(0).norm() < 0.02


def test_random_hemisphere_is_seeded():
    a, b, c = o.random_hemisphere(50, 1), o.random_hemisphere(50, 1), o.random_hemisphere(50, 2)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert bool((a[:, 2] >= 0).all()) and torch.allclose(a.norm(dim=1), torch.ones(50, dtype=torch.float64))


def test_2d_angles_cover_half_turn():
    a = o.angles_2d(6)
    assert torch.allclose(a, torch.tensor([0, 30, 60, 90, 120, 150], dtype=torch.float64))
    d = o.directions_2d(a)
    assert torch.allclose(d[3], torch.tensor([0.0, 1.0], dtype=torch.float64), atol=1e-12)


def test_paper_grid_matches_its_formula():
    v = o.paper_grid(3, 4)
    assert v.shape == (12, 3)
    t, p = math.radians(30), math.radians(90)
    assert torch.allclose(v[1 * 4 + 1], torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p),
                                                      math.cos(t)], dtype=torch.float64))


def test_rig_angles_to_directions():
    v = o.rig_to_direction([0, 90, 90, 30], [0, 0, 90, 45])
    assert torch.allclose(v[0], torch.tensor([0, 0, 1.0], dtype=torch.float64))
    assert torch.allclose(v[1], torch.tensor([1.0, 0, 0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(v[2], torch.tensor([0, -1.0, 0], dtype=torch.float64), atol=1e-12)
    # the tilt is the polar angle from the object's z axis, whatever the spin
    assert abs(math.degrees(math.acos(v[3, 2].item())) - 30) < 1e-9


@pytest.mark.parametrize("k", [0, -3, 2.5])
def test_bad_counts(k):
    with pytest.raises(ValueError):
        o.fibonacci_hemisphere(k)


def test_make_directions_names():
    assert o.make_directions("fibonacci", 10, 3).shape == (10, 3)
    assert o.make_directions("uniform", 10, 2).shape == (10, 2)
    with pytest.raises(ValueError, match="unknown orientation set"):
        o.make_directions("spiral", 10, 3)
