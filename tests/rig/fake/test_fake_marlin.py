"""The fake Marlin 2.x controller (dipnet.rig.fake.marlin): line numbers and checksums checked as the firmware
does, resend requests, keep-alives while a move runs, positions the driver's parser reads, halt and restart."""

from __future__ import annotations

import pytest

from dipnet.rig import marlin
from dipnet.rig.fake.marlin import MarlinDevice

from fake_talk import ball_world, replies


def test_start_banner_then_numbered_lines_with_checksums():
    world = ball_world()
    dev = MarlinDevice(world)
    assert replies(dev)[:2] == ["start", "echo:Marlin 2.1.2.1"]
    assert replies(dev, marlin.numbered(0, "M110 N0")) == ["ok"]
    assert replies(dev, marlin.numbered(1, "G0 Z-15 A20")) == ["ok"]
    assert (world.position().lower_mm, world.position().tilt_deg) == pytest.approx((15.0, 20.0))
    position = replies(dev, marlin.numbered(2, "M114"))
    assert position[-1] == "ok"
    assert marlin.parse_position(position[0]) == pytest.approx({"X": 0.0, "Y": 0.0, "Z": -15.0, "A": 20.0, "B": 0.0,
                                                                "E": 0.0})


def test_a_bad_checksum_or_a_skipped_number_asks_for_a_resend():
    dev = MarlinDevice(ball_world())
    replies(dev)
    replies(dev, marlin.numbered(0, "M110 N0"))
    good = marlin.numbered(1, "G0 Z-5")
    corrupted = good[:good.rindex("*") + 1] + str((int(good.rsplit("*", 1)[1]) + 1) % 256)
    assert replies(dev, corrupted) == ["Error:checksum mismatch, Last Line: 0", "Resend: 1", "ok"]
    assert replies(dev, marlin.numbered(2, "G0 Z-5")) == ["Error:Line Number is not Last Line Number+1, Last Line: 0",
                                                          "Resend: 1", "ok"]
    assert replies(dev, good) == ["ok"]
    for line, expected in (("M110 N7", ["ok"]), (marlin.numbered(8, "G90"), ["ok"])):  # M110 sets the number
        assert replies(dev, line) == expected


def test_a_move_waited_for_sends_keep_alives_then_ok():
    world = ball_world(move_s=0.3, keepalive_s=0.08)
    dev = MarlinDevice(world)
    replies(dev)
    assert replies(dev, "G0 Z-30") == ["ok"] and world.moving()
    waited = replies(dev, "M400", timeout=0.5)
    assert waited[-1] == "ok" and set(waited[:-1]) == {"echo:busy: processing"} and len(waited) - 1 >= 2
    assert not world.moving() and world.position().lower_mm == pytest.approx(30.0)
    assert replies(dev, "G28", timeout=0.5)[-1] == "ok" and world.position().lower_mm == 0.0


def test_unknown_commands_are_echoed_and_a_halt_needs_m999():
    world = ball_world(faults=[{"kind": "alarm", "at_move": 1}])
    dev = MarlinDevice(world)
    replies(dev)
    assert replies(dev, "G999") == ['echo:Unknown command: "G999"', "ok"]
    stopped = "Error:Printer stopped due to errors. Fix the error and use M999 to restart."
    assert replies(dev, "G0 Z-5") == [stopped, "ok"]
    assert replies(dev, "G0 Z-6") == [stopped, "ok"]  # every command refused ...
    assert replies(dev, "M999") == ["ok"] and replies(dev, "G0 Z-6") == ["ok"]  # ... until M999


def test_steps_per_unit_are_reported_as_marlin_2_reports_them_and_set_by_m92():
    """``M92`` alone: the bare report line (``M92_report(forReplay=true)``, no ``echo:``); ``M503``: after ``echo:``;
    ``M92 Z200`` sets Z, and the counts follow while the position in mm stays."""
    dev = MarlinDevice(ball_world())
    replies(dev)
    assert replies(dev, "M92") == ["M92 X80.00 Y80.00 Z400.00 A8.89 B8.89 E500.00", "ok"]
    assert "echo:  M92 X80.00 Y80.00 Z400.00 A8.89 B8.89 E500.00" in replies(dev, "M503")
    assert replies(dev, "G0 Z-15") == ["ok"]
    assert marlin.parse_counts(replies(dev, "M114")[0])["Z"] == -15 * 400
    assert replies(dev, "M92 Z200") == ["ok"]
    position = replies(dev, "M114")[0]
    assert marlin.parse_counts(position)["Z"] == -15 * 200 and marlin.parse_position(position)["Z"] == -15.0


def test_an_older_marlin_reports_no_steps_per_unit():
    """In Marlin 1.x ``M92`` alone answers ``ok``; ``DISABLE_M503`` leaves ``M503`` unknown."""
    dev = MarlinDevice(ball_world(marlin_reports_steps=False))
    replies(dev)
    assert replies(dev, "M92") == ["ok"]
    assert replies(dev, "M503") == ['echo:Unknown command: "M503"', "ok"]


def test_a_workspace_offset_moves_in_logical_coordinates_and_counts_in_machine_ones():
    """``G92 Z0`` at machine Z -10 makes logical = machine + 10: ``G0 Z-5`` goes to machine Z -15, reported as
    ``Z:-5.00`` and counted as -15 mm; ``G28`` clears it, and an ``M206`` offset kept by the world (its EEPROM) survives
    homing."""
    world = ball_world()
    dev = MarlinDevice(world)
    replies(dev)
    replies(dev, "G0 Z-10")
    assert replies(dev, "G92 Z0") == ["ok"]
    assert replies(dev, "G0 Z-5") == ["ok"] and world.position().lower_mm == pytest.approx(15.0)
    position = replies(dev, "M114")[0]
    assert marlin.parse_position(position)["Z"] == pytest.approx(-5.0) and marlin.parse_counts(position)["Z"] == -6000
    replies(dev, "G28")
    replies(dev, "G0 Z-5")
    assert world.position().lower_mm == pytest.approx(5.0)
    kept = ball_world(marlin_offset={"Z": -7.0})
    dev = MarlinDevice(kept)
    replies(dev)
    replies(dev, "G28")
    replies(dev, "G0 Z-10")
    position = replies(dev, "M114")[0]
    assert kept.position().lower_mm == pytest.approx(3.0) and marlin.parse_counts(position)["Z"] == -1200


def test_a_stall_stops_the_stage_half_way_says_endstops_hit_and_the_planner_keeps_the_target():
    """A ``stall`` on the second move (Z -10 to -30): the stage stops at 20 mm; ``echo:endstops hit:`` names the axis
    where it stopped; ``M114`` reports the target (Marlin 2.x: the planner's position), and a later move keeps the
    20 mm deficit (the steppers move by the change of the planned position)."""
    world = ball_world(faults=[{"kind": "stall", "at_move": 2}])
    dev = MarlinDevice(world)
    replies(dev)
    replies(dev, "G0 Z-10")
    assert replies(dev, "G0 Z-30") == ["ok", "echo:endstops hit:  Z:-20.00"]
    assert world.position().lower_mm == pytest.approx(20.0)
    position = replies(dev, "M114")[0]
    assert marlin.parse_position(position)["Z"] == -30.0 and marlin.parse_counts(position)["Z"] == -12000
    replies(dev, "G0 Z-40")
    assert world.position().lower_mm == pytest.approx(30.0)
