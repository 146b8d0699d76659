"""The fake rig's world (dipnet.rig.fake.world): its physics is the simulator's (solve_dip)."""

from __future__ import annotations

import numpy as np
import pytest

from dipnet.core.orientations import rig_to_direction
from dipnet.simulator.physics import solve_dip


def test_fake_physics_matches_solve_dip(world):
    world.reset()
    for lower, tilt, spin in ((40.0, 0.0, 0.0), (55.0, 30.0, 70.0), (95.0, 60.0, 10.0)):
        world.start_move({"lower_mm": lower, "tilt_deg": tilt, "spin_deg": spin})
        state = solve_dip(world.shape, rig_to_direction(tilt, spin)[0].numpy(), world.tank, np.array([lower]),
                          world.waterline_start(tilt))
        assert world.rise_mm() == pytest.approx(state.rise_mm[0], abs=2e-4)
