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


@pytest.mark.parametrize(("option", "value"), [("level_sigma_mm", -1.0), ("level_sigma_mm", float("nan")),
                                               ("balance_sigma_g", -0.5), ("level_quantum_mm", -0.001),
                                               ("move_s", -1.0), ("latency_s", float("inf"))])
def test_a_negative_or_nan_noise_or_time_of_the_fake_rig_is_refused(meshes_dir, option, value):
    """scan.py rig.fake.level_sigma_mm=-1 (or nan) scanned noise-free readings, exit 0, without a word
    (``sigma > 0`` was false): the option asked for noise and got none."""
    from dipnet.rig.fake.world import FakeRig
    from dipnet.shapes import load_mesh

    shape = load_mesh(meshes_dir / "torus.ply", radius=42.0)
    with pytest.raises(ValueError, match=rf"rig\.fake\.{option} must be a finite number >= 0 \(0: none\), got"):
        FakeRig(shape, **{option: value})
