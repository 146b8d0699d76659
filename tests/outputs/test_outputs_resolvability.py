"""What the plan resolves, into the run directory (dipnet.outputs.resolvability): resolvability.npz and its
figure, and the summary metrics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.evaluation.resolvability import Resolvability, resolvability
from dipnet.outputs.resolvability import plot_resolvability, write_resolvability

GRID = Grid(24, 3, 100.0)


def test_outputs_are_written(tmp_path):
    """The authors' robot plan (tilts 0-35 deg every 5 deg, spins 0-340 deg every 20 deg): the file holds the
    frequency coverage on the grid and the missing cone; the figure is drawn."""
    tilt, spin = np.meshgrid(np.arange(0, 36, 5.0), np.arange(0, 360, 20.0), indexing="ij")
    res = resolvability(rig_to_direction(tilt.ravel(), spin.ravel()), GRID, diameter_mm=60.0)
    assert isinstance(res, Resolvability) and res.diameter_mm == 60.0
    saved = np.load(res.save(tmp_path / "resolvability.npz"))
    assert saved["coverage"].shape == GRID.shape
    assert float(saved["missing_cone_deg"]) == pytest.approx(res.missing_cone_deg)
    assert plot_resolvability(res, tmp_path / "resolvability.png").stat().st_size > 10_000


@pytest.mark.parametrize("figure", [True, False])
def test_write_resolvability_fills_the_run_directory_and_returns_the_metrics(tmp_path, figure):
    directions = fibonacci_hemisphere(12)
    measurement = DipMeasurement(directions, torch.ones(12, 24, dtype=torch.float64), GRID.voxel_size,
                                 torch.full((12,), -GRID.extent / 2, dtype=torch.float64))
    metrics = write_resolvability(measurement, GRID, tmp_path, figure=figure)
    assert metrics == resolvability(directions, GRID, measurement).metrics()
    with np.load(tmp_path / "resolvability.npz") as saved:
        assert float(saved["missing_cone_deg"]) == pytest.approx(metrics["missing_cone_deg"])
    assert (tmp_path / "resolvability.png").exists() == figure
