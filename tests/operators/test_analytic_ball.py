"""The analytic ball: its cumulative volume, exact profiles and supersampled occupancy agree with closed forms."""

import math

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators.analytic import ball_below, ball_occupancy, ball_profiles


@pytest.mark.parametrize("ndim,full", [(3, 4 / 3 * math.pi * 10.0**3), (2, math.pi * 10.0**2)])
def test_the_volume_below_runs_from_nothing_to_the_whole_ball(ndim, full):
    u = torch.tensor([-20.0, -10.0, 0.0, 10.0, 20.0], dtype=torch.float64)
    below = ball_below(u, 10.0, ndim)
    assert torch.allclose(below, torch.tensor([0.0, 0.0, full / 2, full, full], dtype=torch.float64), atol=1e-9)
    assert (torch.diff(ball_below(torch.linspace(-10, 10, 101, dtype=torch.float64), 10.0, ndim)) >= 0).all()


def test_profiles_of_a_shifted_ball_sum_to_its_volume_and_move_with_it():
    edges = torch.linspace(-30, 30, 13, dtype=torch.float64)
    directions = fibonacci_hemisphere(5)
    centred = ball_profiles(directions, edges, torch.zeros(3), 10.0)
    assert torch.allclose(centred.sum(dim=1), torch.full((5,), 4 / 3 * math.pi * 1000.0, dtype=torch.float64))
    up = ball_profiles(torch.tensor([[0.0, 0.0, 1.0]]), edges, torch.tensor([0.0, 0.0, 5.0]), 10.0)
    still = ball_profiles(torch.tensor([[0.0, 0.0, 1.0]]), edges, torch.zeros(3), 10.0)
    assert torch.allclose(up[0, 1:], still[0, :-1])  # one 5 mm slab higher


def test_the_supersampled_occupancy_holds_the_balls_volume():
    grid = Grid(32, 3, 64.0)
    occupancy = ball_occupancy(grid, torch.zeros(3), 20.0)
    assert float(occupancy.sum()) * grid.voxel_volume == pytest.approx(4 / 3 * math.pi * 20.0**3, rel=5e-3)
    assert float(occupancy.min()) >= 0 and float(occupancy.max()) <= 1
