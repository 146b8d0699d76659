"""DeepImagePriorSolver: an untrained decoder fitted to the dips recovers simple shapes, by seed."""

from __future__ import annotations

import math

import pytest
import torch

from solver_helpers import one_thread, partial_volume  # noqa: F401 (one_thread: autouse fixture)
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.evaluation.metrics import iou
from dipnet.operators import make_operator
from dipnet.solvers.deep_image_prior import DeepDecoder, DeepImagePriorSolver


def ball_problem(grid: Grid, directions: torch.Tensor, radius: float = 0.6):
    """``(truth, operator, noise-free measurement)`` of a ball of ``radius`` x the working radius, off centre."""
    centre = torch.tensor([0.15, -0.1, 0.05][:grid.ndim], dtype=torch.float64) * grid.radius
    truth = partial_volume(grid, lambda p: (p - centre).norm(dim=-1) < radius * grid.radius)
    op = make_operator(grid, directions, backend="splat")
    with torch.no_grad():
        profiles = op(truth)
    k = op.n_orientations
    return truth, op, DipMeasurement(op.directions, profiles, op.slab_thickness, op.slab_edges()[:1].expand(k))


def test_decoder_makes_the_grid_and_depends_on_its_seed():
    torch.manual_seed(0)
    a = DeepDecoder((24, 24, 24), channels=4, levels=2, fine_kernel=1)
    assert tuple(a().shape) == (24, 24, 24) and a.sizes == [6, 12, 24]
    assert tuple(DeepDecoder((30, 30), channels=4, levels=3)().shape) == (30, 30)
    torch.manual_seed(0)
    b = DeepDecoder((24, 24, 24), channels=4, levels=2, fine_kernel=1)
    assert torch.equal(a(), b())


def test_reconstructs_a_disc_and_is_deterministic_by_seed():
    truth, op, meas = ball_problem(Grid(32, 2), directions_2d(angles_2d(8, start_deg=5.0)))
    a = DeepImagePriorSolver(iterations=150, seed=1, progress=False).solve(meas, op)
    b = DeepImagePriorSolver(iterations=150, seed=1, progress=False).solve(meas, op)
    c = DeepImagePriorSolver(iterations=150, seed=2, progress=False).solve(meas, op)
    assert iou(a.binary, truth > 0.5) >= 0.95
    assert torch.equal(a.occupancy, b.occupancy) and a.history == b.history
    assert not torch.equal(a.occupancy, c.occupancy)
    assert 0 <= float(a.occupancy.min()) <= float(a.occupancy.max()) <= 1
    assert float(a.occupancy[~op.mask].abs().max()) == 0.0
    assert a.info["solver"] == "dip" and a.info["network_weights"] > 0 \
        and a.history["data"][-1] < 0.01 * a.history["data"][0]


@pytest.mark.slow
def test_reconstructs_a_ball_at_24_cubed():
    truth, op, meas = ball_problem(Grid(24, 3), fibonacci_hemisphere(16))
    rec = DeepImagePriorSolver(iterations=400, progress=False).solve(meas, op)
    assert iou(rec.binary, truth > 0.5) >= 0.9


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="warm_start"):
        DeepImagePriorSolver(warm_start=torch.zeros(8, 8))
    with pytest.raises(ValueError, match="odd kernel_size"):
        DeepImagePriorSolver(kernel_size=2)
    with pytest.raises(ValueError, match="temperature"):
        DeepImagePriorSolver(temperature_start=0.1, temperature_end=1.0)
    with pytest.raises(ValueError, match="need finite temperatures"):
        DeepImagePriorSolver(temperature_start=math.inf, temperature_end=math.inf)  # was: a NaN loss once solving
    with pytest.raises(ValueError, match="cubic"):
        DeepDecoder((8, 9))


@pytest.mark.parametrize("options", [{"fine_kernel": 2}, {"fine_kernel": -1}, {"fine_kernel": 1.5},
                                     {"channels": 1.5}, {"levels": True}])
def test_network_sizes_that_cannot_make_the_grid_are_named(options):
    """An even ``fine_kernel`` made a 17^3 output for a 16^3 grid (a size-mismatch traceback at the first step),
    a negative or fractional one a tensor-size traceback."""
    with pytest.raises(ValueError, match="need whole numbers channels >= 1, levels >= 1, an odd kernel_size"):
        DeepImagePriorSolver(**options)
