"""Air pockets and vessels (dipnet.simulator.pockets): trapped air and dry cavities against the chamber's volume."""

from __future__ import annotations

import numpy as np
import pytest

from dipnet.shapes import Ball, Box
from dipnet.shapes.analytic import ChamberBox, Torus
from dipnet.simulator.physics import LevelSensor, Tank, simulate_scan
from dipnet.simulator.pockets import CavityGrid, Pockets, as_pockets, cavity_shares

HALF, CHAMBER, CHANNEL = 26.0, 13.0, 3.9  # mm: box and chamber half sizes, channel half width
BOX = ChamberBox([HALF] * 3, chamber_half_sizes=CHAMBER, channel_half_width=CHANNEL)  # channel along +z
CHAMBER_VOLUME = (2 * CHAMBER) ** 3
CHANNEL_VOLUME = (2 * CHANNEL) ** 2 * (HALF - CHAMBER)
UP, DOWN, SIDE = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def grid() -> CavityGrid:
    return CavityGrid(BOX, 96)


def test_a_channel_pointing_down_traps_the_chamber_and_channel_as_air(grid):
    pocket, vessel = grid.shares(DOWN)
    assert pocket == pytest.approx(CHAMBER_VOLUME + CHANNEL_VOLUME, rel=0.06)
    assert vessel == 0.0


def test_a_channel_pointing_up_keeps_the_chamber_dry_as_a_vessel(grid):
    pocket, vessel = grid.shares(UP)
    assert vessel == pytest.approx(CHAMBER_VOLUME + CHANNEL_VOLUME, rel=0.06)
    assert pocket == 0.0


def test_a_sideways_channel_traps_the_chamber_above_it_and_keeps_the_part_below_it_dry(grid):
    # the channel spans |x| < CHANNEL: air above its ceiling cannot leave, water reaches below its floor last
    pocket, vessel = grid.shares(SIDE)
    beside = CHAMBER_VOLUME * (CHAMBER - CHANNEL) / (2 * CHAMBER)
    assert pocket == pytest.approx(beside, rel=0.12)
    assert vessel == pytest.approx(beside, rel=0.12)


@pytest.mark.parametrize("shape", [Ball(30.0), Box([30.0, 20.0, 10.0]), Torus(25.0, 10.0)], ids=lambda s: s.name)
def test_shapes_without_cavities_trap_nothing(shape):
    dirs = np.random.default_rng(0).normal(size=(4, 3))
    assert np.all(cavity_shares(shape, dirs / np.linalg.norm(dirs, axis=1, keepdims=True), resolution=48) == 0.0)


def test_pockets_leave_the_dips_of_a_ball_as_they_were():
    dirs = np.array([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    plain = simulate_scan(Ball(30.0), dirs, progress=False)
    trapped = simulate_scan(Ball(30.0), dirs, pockets=True, progress=False)
    for a, b in zip(plain.orientations, trapped.orientations):
        np.testing.assert_array_equal(a.values, b.values)
    assert trapped.header.config["pockets"] == {"resolution": 64}
    assert all(o.meta["pocket_mm3"] == o.meta["vessel_mm3"] == 0.0 for o in trapped.orientations)
    assert "pocket_mm3" not in plain.orientations[0].meta


def test_dips_displace_the_trapped_air_and_the_dry_vessel_until_it_floods(grid):
    tank = Tank(cross_section_mm2=60000.0)
    scan = simulate_scan(BOX, np.stack([DOWN, UP]), tank=tank, sensor=LevelSensor(), pockets=Pockets(96),
                         progress=False)
    down, up = ((o.values - tank.rest_level_mm) * tank.cross_section_mm2 for o in scan.orientations)
    # channel down: the air stays, every reading is monotone and the dip ends at V + the pocket
    assert np.all(np.diff(down) >= -1e-6)
    assert down[-1] == pytest.approx(BOX.volume + grid.shares(DOWN)[0], rel=1e-6)
    # channel up: the chamber displaces water until the water reaches the channel's mouth, then floods
    assert up.max() - up[-1] == pytest.approx(grid.shares(UP)[1], rel=0.02)
    assert up[-1] == pytest.approx(BOX.volume, rel=1e-6)
    assert max(o.meta["residual_mm3"] for o in scan.orientations) < 1e-6 * BOX.volume
    # each dip records what it trapped
    assert [o.meta["pocket_mm3"] for o in scan.orientations] == [grid.shares(DOWN)[0], 0.0]
    assert [o.meta["vessel_mm3"] for o in scan.orientations] == [0.0, grid.shares(UP)[1]]


def test_a_2d_chamber_traps_its_air_too():
    box = ChamberBox([HALF] * 2, chamber_half_sizes=CHAMBER, channel_half_width=CHANNEL)
    pocket, vessel = CavityGrid(box, 128).shares(np.array([0.0, -1.0]))
    assert pocket == pytest.approx((2 * CHAMBER) ** 2 + 2 * CHANNEL * (HALF - CHAMBER), rel=0.05)
    assert vessel == 0.0


def test_a_channel_narrower_than_a_cell_is_named():
    box = ChamberBox([HALF] * 3, chamber_half_sizes=CHAMBER, channel_half_width=0.4)
    with pytest.warns(RuntimeWarning, match="no path to the open water.*raise pockets.resolution"):
        pocket, vessel = CavityGrid(box, 24).shares(DOWN)
    assert pocket == vessel == 0.0  # taken as wet


@pytest.mark.parametrize("value, message", [(4, "in \\[8, 256\\]"), (64.5, "whole number"), (True, "whole number")])
def test_a_bad_resolution_is_named(value, message):
    with pytest.raises(ValueError, match=message):
        Pockets(value)


def test_the_pockets_option_takes_a_flag_or_a_model():
    assert as_pockets(None) is None and as_pockets(False) is None
    assert as_pockets(True) == Pockets()
    assert as_pockets(Pockets(32)).resolution == 32
    assert as_pockets({"resolution": 96}) == Pockets(96)  # a config's {resolution: 96}
    with pytest.raises(ValueError, match="unknown option\\(s\\) cells"):
        as_pockets({"cells": 96})
    with pytest.raises(ValueError, match="pockets must be true, false, null or \\{resolution"):
        as_pockets("yes")
