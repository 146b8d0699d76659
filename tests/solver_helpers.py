"""Helpers shared by the optimisation-solver tests."""

from __future__ import annotations

import itertools

import pytest
import torch

from dipnet.grid import Grid


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small problems run faster on one thread, and the test machine is shared."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def partial_volume(grid: Grid, inside, sub: int = 3) -> torch.Tensor:
    """Occupancy fractions of an analytic solid ``inside(points (..., d) mm) -> bool``, float64."""
    centres, acc = grid.centers(), torch.zeros(grid.shape, dtype=torch.float64)
    for s in itertools.product(range(sub), repeat=grid.ndim):
        acc += inside(centres + ((torch.tensor(s, dtype=torch.float64) + 0.5) / sub - 0.5) * grid.voxel_size)
    return acc / sub**grid.ndim
