"""What every controller driver shares (dipnet.rig.controller): the axis map between rig coordinates and machine
words."""

from __future__ import annotations

import pytest

from dipnet.rig.controller import Axis, AxisMap, ControllerError, Position


def test_axis_map_round_trip_and_words():
    axes = AxisMap(lower=Axis("Z", scale=2.0, sign=-1, offset=5.0), tilt=Axis("A", scale=10.0), spin=Axis("B"))
    assert axes.words(12.5, 3.0, None) == "Z-20.0000 A30.0000"
    pos = axes.rig_position({"Z": -20.0, "A": 30.0, "B": 7.0, "X": 0.0})
    assert pos == Position(12.5, 3.0, 7.0)
    with pytest.raises(ControllerError, match="no B axis"):
        axes.rig_position({"Z": 0.0, "A": 0.0})
    with pytest.raises(ValueError, match="distinct"):
        AxisMap(lower=Axis("Z"), tilt=Axis("Z"), spin=Axis("B"))
    cfg = AxisMap.from_config({"tilt": {"letter": "X"}, "spin": {"letter": "Y", "sign": -1}})
    assert (cfg.lower.letter, cfg.lower.sign, cfg.tilt.letter, cfg.spin.sign) == ("Z", -1, "X", -1)
