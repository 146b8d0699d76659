"""Shared pieces of the planning and uncertainty tests: the reconstruction config, rig angles of directions, and
a chamber box with dips simulated along any plan."""

from __future__ import annotations

import numpy as np
import torch
from hydra import compose, initialize_config_module

from dipnet.core.grid import Grid
from dipnet.shapes import builtin_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement


def tilt_spin(directions):
    """``(tilt, spin)`` in degrees of unit directions ``(N, 3)`` (the rig's convention)."""
    d = torch.as_tensor(directions).numpy()
    return np.degrees(np.arccos(np.clip(d[:, 2], -1, 1))), np.mod(np.degrees(np.arctan2(-d[:, 1], d[:, 0])), 360)


def reconstruct_cfg(*overrides):
    """The reconstruction config (``conf/config.yaml``) with ``overrides``, progress bars off."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=["output.progress=false", *overrides])


def box_problem():
    """A chamber box at 20^3, its true occupancy and dips simulated along a plan (30 dB)."""
    grid = Grid(20, 3)
    shape = builtin_shape("chamber_box", 3, 0.9 * grid.radius)
    truth = shape.occupancy(grid, supersample=2).numpy()

    def dips(directions):
        _, measurement = simulate_measurement(shape, directions, grid=grid, sensor=LevelSensor(snr_db=30, seed=1),
                                              progress=False)
        return measurement

    return grid, truth, dips
