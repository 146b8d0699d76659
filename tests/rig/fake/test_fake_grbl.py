"""The fake GRBL 1.1 controller (dipnet.rig.fake.grbl), byte by byte as the real firmware answered in the recorded
traces: banner and alarm at power-up, homing, status reports the driver's parser reads, errors, soft limits,
feed hold, soft reset."""

from __future__ import annotations

import pytest

from dipnet.rig import grbl_dialect
from dipnet.rig.fake.grbl import GrblDevice

from fake_talk import ball_world, replies


def status(dev: GrblDevice) -> grbl_dialect.GrblStatus:
    (line,) = replies(dev, b"?")
    return grbl_dialect.parse_status(line)


def test_power_up_in_alarm_until_homed():
    world = ball_world()
    dev = GrblDevice(world)
    assert replies(dev) == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert status(dev).state == "Alarm"
    assert replies(dev, "G0 Z-10") == ["error:9"]  # locked: no motion
    assert replies(dev, "$H") == ["ok"]
    assert status(dev).state == "Idle" and world.position().lower_mm == 0.0


def test_a_move_lands_where_the_status_says():
    world = ball_world()
    dev = GrblDevice(world)
    replies(dev, "$H")
    assert replies(dev, "G0 Z-12.5 A10 B-30") == ["ok"]
    pos = world.position()
    assert (pos.lower_mm, pos.tilt_deg, pos.spin_deg) == pytest.approx((12.5, 10.0, -30.0))
    assert status(dev).mpos == pytest.approx({"X": 0.0, "Y": 0.0, "Z": -12.5, "A": 10.0, "B": -30.0})
    assert replies(dev, "G4 P0") == ["ok"]  # the dwell answers when the move is over


def test_settings_build_info_and_unknown_commands():
    dev = GrblDevice(ball_world(grbl_settings={22: 0}))
    assert replies(dev) == ["Grbl 1.1h ['$' for help]"]  # no homing: no alarm at power-up
    settings = replies(dev, "$$")
    assert settings[-1] == "ok" and "$22=0" in settings and "$130=200.000" in settings
    assert replies(dev, "$I") == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]
    assert replies(dev, "$H") == ["error:5"]  # homing disabled
    assert replies(dev, "T1 nonsense") == ["error:20"]
    assert replies(dev, "G90") == ["ok"] and replies(dev, "$10=0") == ["ok"]
    assert status(dev).fields.get("WPos") is not None  # $10=0: work positions in the reports


def test_a_move_past_the_soft_limits_is_alarm_2_and_then_only_a_reset_is_heard():
    world = ball_world(grbl_settings={20: 1})
    dev = GrblDevice(world)
    replies(dev, "$H")
    assert replies(dev, "G0 Z-500") == ["ALARM:2", "[MSG:Reset to continue]"]
    assert replies(dev, "$X") == [] and replies(dev, b"?") == []  # critical: silent
    assert replies(dev, b"\x18") == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert world.position().lower_mm == 0.0


def test_feed_hold_then_resume_and_a_reset_while_moving_loses_the_position():
    world = ball_world(move_s=0.4)
    dev = GrblDevice(world)
    replies(dev, "$H", timeout=0.5)
    assert replies(dev, "G0 Z-20") == ["ok"] and world.moving()
    replies(dev, b"!")
    assert [status(dev).state, status(dev).state] == ["Hold", "Hold"]
    held = world.position().lower_mm
    assert 0.0 < held < 20.0 and not world.moving()
    replies(dev, b"~")
    assert world.moving() and status(dev).state == "Run"
    assert replies(dev, b"\x18")[0] == "ALARM:3" and world.alarm  # reset mid-move: position lost
