"""The Marlin driver (dipnet.rig.marlin): a recorded-style transcript classified, line checksums, a resend request
recovered on the fake rig."""

from __future__ import annotations

import functools
import operator

from dipnet.rig import marlin

from rig_helpers import plan_for, scan

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
