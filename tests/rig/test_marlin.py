"""The Marlin driver (dipnet.rig.marlin): a recorded-style transcript classified, line checksums, a resend request
recovered on the fake rig."""

from __future__ import annotations

import functools
import operator

import pytest

from dipnet.rig import marlin

from rig_helpers import ORIGIN, make_runner, make_world, plan_for, scan

# A Marlin 2.x session with keep-alives, a checksum error and a halt.
MARLIN_TRANSCRIPT = """\
start
echo:Marlin 2.1.2.1
echo: Last Updated: 2023-05-25 | Author: (none)
ok
echo:busy: processing
busy: processing
X:0.00 Y:0.00 Z:-25.00 A:10.00 B:40.00 E:0.00 Count X:0 Y:0 Z:-10000 A:800 B:3200
ok P15 B3
Error:checksum mismatch, Last Line: 11
Resend: 12
echo:Unknown command: "G999"
Error:Printer halted. kill() called!
"""


def test_marlin_transcript_classification():
    kinds = [marlin.classify(line) for line in MARLIN_TRANSCRIPT.splitlines()]
    assert [k.kind for k in kinds] == ["start", "echo", "echo", "ok", "busy", "busy", "position", "ok",
                                       "error", "resend", "echo", "fatal"]
    assert kinds[9].number == 12
    assert marlin.classify("rs N7").number == 7
    assert marlin.parse_position(MARLIN_TRANSCRIPT.splitlines()[6]) == {
        "X": 0.0, "Y": 0.0, "Z": -25.0, "A": 10.0, "B": 40.0, "E": 0.0}
    assert marlin.parse_position("echo:busy: processing") == {}


def test_marlin_checksum():
    # OctoPrint's well-known first line
    assert marlin.numbered(0, "M110 N0") == "N0 M110 N0*125"
    text = "N12 G0 Z-10.0000 A5.0000"
    assert marlin.checksum(text) == functools.reduce(operator.xor, text.encode("ascii"))


def test_marlin_resend_is_recovered(world, tmp_path):
    world.reset(faults=[{"kind": "resend", "at_move": 5}])
    raw = scan(world, "marlin", "level", plan_for(1, step=10.0), tmp_path / "scan.jsonl")
    assert len(raw.completed()) == 1 and world.fired and world.fired[0].kind == "resend"


def test_a_port_that_streams_other_lines_is_not_waited_on_forever(world):
    """``rig=fake_marlin rig.controller.url=`` the level sensor's port (the two USB ports swapped). Before: every
    sensor line restarted the wait for ``ok``, so connecting never ended (killed after 60 s); now the time limit
    holds and the message names the line and the likely slip. Keep-alives (``echo:busy``) still extend it."""
    import time

    import pytest

    from dipnet.rig.controller import RigTimeout

    world.reset()
    ctl = marlin.MarlinController(world.url("level"), timeout=0.3)
    start = time.monotonic()
    with pytest.raises(RigTimeout, match=r"^no 'ok' to 'M110 N0' from fakerig://testrig/level within 0\.3 s; it "
                                         r"sent \d+ other line\(s\), the last 'L=\d+\.\d{3} mm': is "
                                         r"rig\.controller\.url the controller's port \(not the sensor's\)\?$"):
        ctl.connect()
    assert time.monotonic() - start < 3.0
    ctl.close()


def test_marlin_counts_and_steps_per_unit_are_parsed():
    """``M114``'s counts (after ``Count``), and the steps per unit of ``M92`` (no ``echo:``) or ``M503``."""
    report = MARLIN_TRANSCRIPT.splitlines()[6]
    assert marlin.parse_counts(report) == {"X": 0, "Y": 0, "Z": -10000, "A": 800, "B": 3200}
    assert marlin.parse_counts("X:0.00 Y:0.00 Z:10.00 E:0.00") == {} and marlin.parse_counts("echo:Count X:3") == {}
    steps = {"X": 80.0, "Y": 80.0, "Z": 400.0, "E": 500.0}
    assert marlin.parse_steps_per_unit(["  M92 X80.00 Y80.00 Z400.00 E500.00", "ok"]) == steps
    assert marlin.parse_steps_per_unit(["echo:; Steps per unit:", "echo:  M92 X80.00 Y80.00 Z400.00 E500.00",
                                        "echo:  M206 X0.00 Y0.00 Z0.00"]) == steps
    assert marlin.parse_steps_per_unit(['echo:Unknown command: "M503"']) == {}


def test_a_healthy_marlin_scan_is_checked_and_passes(world, tmp_path, caplog):
    """Every move is checked against the counts (the steps per unit were read at connect: those the fake uses, the
    rotary ones printed to two decimals) and none differs: the scan completes without a warning."""
    from dipnet.rig.fake.world import MARLIN_STEPS

    world.reset()
    runner = make_runner(world, "marlin", "level", plan_for(2, step=10.0), tmp_path / "scan.jsonl")
    assert len(runner.run().completed()) == 2
    read = runner.controller.steps_per_unit
    assert read["Z"] == MARLIN_STEPS["Z"] and abs(read["B"] - MARLIN_STEPS["B"]) <= marlin.M92_ROUNDING
    assert "not checking" not in caplog.text


def test_marlin_lost_steps_stop_the_scan_before_the_next_reading(world, tmp_path):
    """A stall (a crash, or stall detection tripping the endstop) half-way through the 7th move, the lowering from 20
    to 30 mm (moves: lift, turn, start height, then one per reading at 0, 10, 20, 30 ... mm): the stage stops at
    25 mm and Marlin says ``endstops hit`` while its planner, and so ``M114``, keeps the target. Before: no check,
    the reading at "30 mm" was taken 5 mm short and the scan went on. Now it stops after 3 readings, does not move
    (the position is lost) and asks to home."""
    from dipnet.core.rawscan import read_rawscan
    from dipnet.rig.runner import ScanAborted

    world.reset(faults=[{"kind": "stall", "at_move": 7}])
    path = tmp_path / "stall.jsonl"
    with pytest.raises(ScanAborted) as info:
        scan(world, "marlin", "level", plan_for(1, step=10.0), path)
    message = str(info.value)
    assert message.startswith("scan stopped at orientation 0 (tilt 60, spin 0), reading 3 at 30 mm: "
                              "PositionMismatch: the controller reported 'echo:endstops hit: Z:-25.00' during the "
                              "move: an axis stopped short")  # the runner's one-line message folds the two spaces
    assert "OBJECT NOT LIFTED" in message and "home=true" in message
    assert read_rawscan(path).orientations[0].n_readings == 3
    assert world.position().lower_mm == pytest.approx(25.0) and not world.moving()


def test_a_marlin_workspace_offset_stops_the_scan_before_anything_is_read(meshes_dir, tmp_path):
    """An ``M206`` home offset saved in the EEPROM (Z -7 mm: logical = machine - 7): ``G0 Z-10`` goes to machine Z -3,
    and ``M114`` says ``Z:-10.00`` (logical) but counts Z -1200 (-3 mm at 400 steps/mm). Before: both dips completed
    with every reading taken 7 mm shallower than recorded. Now the first move (the lift to 0 mm, machine Z +7) stops
    the scan, before the object is turned or anything is recorded."""
    from dipnet.core.rawscan import read_rawscan
    from dipnet.rig.runner import ScanAborted

    offset = make_world(meshes_dir, "m206", marlin_offset={"Z": -7.0})
    path = tmp_path / "offset.jsonl"
    with pytest.raises(ScanAborted) as info:
        scan(offset, "marlin", "level", plan_for(2, step=10.0), path)
    assert str(info.value).startswith(
        "scan stopped at orientation 0 (tilt 41.4096, spin 0): PositionMismatch: idle after the move, the controller "
        "counts lower -7.000 mm (commanded 0, Z count 2800 at 400 steps/unit): the machine is not where the scan sent "
        "it, and no reading is recorded there. Marlin moves in logical coordinates and counts steps in its own: clear "
        "a work offset (G92")
    assert read_rawscan(path).orientations == [] and offset.position().tilt_deg == 0.0


def test_a_marlin_spin_axis_that_wraps_goes_the_short_way_and_passes(meshes_dir, tmp_path):
    """Spin on B with ``wrap: 360``: spins 120, 240, then 10 deg, commanded as 370 deg (the short way from 240 deg);
    the counts (370 deg at 8.888... steps/deg, which M92 prints as 8.89) agree within a step plus the printing's
    rounding, so the scan completes and the stage stands at 370 deg."""
    import numpy as np

    from dipnet.rig.controller import AxisMap
    from dipnet.rig.runner import ScanPlan

    axes = AxisMap.from_config({"spin": {"letter": "B", "wrap": 360.0}})
    spinning = make_world(meshes_dir, "wrapping", axes=axes)
    plan = ScanPlan([(30.0, 120.0), (30.0, 240.0), (30.0, 10.0)], start_mm=0.0, stop_mm=40.0, step_mm=10.0, safe_mm=0.0,
                    origin_height_mm=ORIGIN)
    raw = scan(spinning, "marlin", "level", plan, tmp_path / "wrap.jsonl", axes=axes)
    assert [o.complete for o in raw.orientations] == [True, True, True]
    assert spinning.position().spin_deg == pytest.approx(370.0)
    for other in raw.orientations[1:]:  # the torus turns about its own axis: the same readings at every spin
        np.testing.assert_allclose(other.values, raw.orientations[0].values, atol=0.05)


def test_a_marlin_that_does_not_report_its_steps_per_unit_says_once_that_arrival_is_not_checked(meshes_dir, tmp_path,
                                                                                                  caplog):
    """Marlin 1.x answers ``M92`` with ``ok`` alone, and ``M503`` may be compiled out: the counts cannot be
    turned into positions. The scan runs, and a single warning says that arrival is not checked."""
    import logging

    silent = make_world(meshes_dir, "nosteps", marlin_reports_steps=False)
    with caplog.at_level(logging.WARNING, logger="dipnet.rig.marlin"):
        raw = scan(silent, "marlin", "level", plan_for(2, step=10.0), tmp_path / "silent.jsonl")
    assert len(raw.completed()) == 2
    warnings = [r.getMessage() for r in caplog.records if "not checking" in r.getMessage()]
    assert warnings == ["not checking that the machine arrives where the scan sends it: the controller reports "
                        "no steps per unit (M92 answers only 'ok' in Marlin 1.x; M503 may be compiled out)"]


def test_steps_per_unit_changed_after_connect_stop_the_marlin_scan(world, tmp_path, monkeypatch):
    """Z's steps per unit become 200 (M92 Z200 from another terminal, or M501 loading other EEPROM values) before the
    5th move, the lowering from 0 to 10 mm: the motor turns 2000 steps, 5 mm on a screw of 400 steps/mm, and Marlin
    counts -2000 (its logical position still says 10 mm). Before: nothing compared, every later reading was taken at
    half the recorded depth. Now the move stops the scan: -2000 steps are -5 mm at the 400 steps/mm read at connect."""
    from dipnet.rig.runner import ScanAborted

    world.reset()
    real = world.on_motion

    def m92_changes():
        if world.motion_count == 4:
            monkeypatch.setitem(world.marlin_steps, "Z", 200.0)
        return real()

    monkeypatch.setattr(world, "on_motion", m92_changes)
    with pytest.raises(ScanAborted) as info:
        scan(world, "marlin", "level", plan_for(1, step=10.0), tmp_path / "m92.jsonl")
    assert ("reading 1 at 10 mm: PositionMismatch: idle after the move, the controller counts lower 5.000 mm "
            "(commanded 10, Z count -2000 at 400 steps/unit)") in str(info.value)
    assert world.position().lower_mm == pytest.approx(0.0)  # lifted: the controller's 0 mm is the stage's 0 mm


def test_a_marlin_software_endstop_that_clamps_the_lowering_stops_the_scan(meshes_dir, tmp_path):
    """Stock Marlin keeps Z in [Z_MIN_POS, Z_MAX_POS] = [0, 200] mm (software endstops on), and the rig lowers towards
    -Z: ``G0 Z-10`` is clamped to Z0 without a word, and ``M114`` reports the clamped position. Before: the stage
    never left 0 mm while the scan recorded 11 readings "at" 0 to 100 mm, all 150 mm, and stopped at the end of the dip
    blaming the sensor (``SensorError: all 11 readings of orientation 0 are 150 mm``). Now the first lowering, to
    10 mm, stops it with the clamped count and the advice (M211)."""
    from dipnet.rig.runner import ScanAborted

    clamped = make_world(meshes_dir, "softlimits", marlin_soft_limits={"Z": (0.0, 200.0)})
    with pytest.raises(ScanAborted) as info:
        scan(clamped, "marlin", "level", plan_for(1, step=10.0), tmp_path / "clamped.jsonl")
    message = str(info.value)
    assert ("reading 1 at 10 mm: PositionMismatch: idle after the move, the controller counts lower 0.000 mm "
            "(commanded 10, Z count 0 at 400 steps/unit)") in message
    assert "inside the software endstops (M211)" in message and "kept 1 readings" in message


def test_line_numbers_given_as_another_word_is_refused():
    """``rig.controller.line_numbers=no`` was kept as the string "no", true: numbered, checksummed lines were sent."""
    with pytest.raises(ValueError, match="rig.controller.line_numbers must be true or false, got 'no'"):
        marlin.MarlinController("loop://", line_numbers="no")
