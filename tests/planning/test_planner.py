"""The next-best-dip planner (dipnet.planning.planner): its picks fill the missing cone, diverse and deterministic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.orientations import Reach
from dipnet.operators import make_operator
from dipnet.planning.planner import NextBestDipPlanner
from dipnet.solvers.minnorm import MinNormSolver

from planning_fixtures import box_problem as make_box_problem
from planning_fixtures import tilt_spin


@pytest.fixture(scope="module")
def box_problem():
    return make_box_problem()


def test_planner_fills_the_missing_cone(box_problem):
    grid, truth, dips = box_problem
    measurement = dips(Reach(tilt_range_deg=(0, 35)).uniform(12))
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = MinNormSolver(progress=False).solve(measurement, operator)
    planner = NextBestDipPlanner(resolution=20)
    chosen = planner.next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    tilt, spin = tilt_spin(chosen)
    assert tilt.min() > 45, tilt
    # the batch is diverse: no two picks measure (nearly) the same planes
    cosines = np.abs(chosen.numpy() @ chosen.numpy().T)[np.triu_indices(4, 1)]
    assert cosines.max() < np.cos(np.radians(15))
    # deterministic: the same dips give the same plan
    again = NextBestDipPlanner(resolution=20).next(measurement, recon, Reach().candidates(), k=4, operator=operator)
    assert torch.equal(again, chosen)
    assert planner.last_seconds < 10
