"""The GRBL driver (dipnet.rig.grbl) on the fake rig: what it says when the port is not a GRBL board's. The recorded
firmware's behaviour: test_grbl_traces.py; the line parsers and settings checks: test_grbl_dialect.py."""

from __future__ import annotations

import pytest

from dipnet.rig.controller import RigTimeout
from dipnet.rig.grbl import GrblController


def test_a_port_that_streams_other_lines_names_them(world):
    """``rig.controller.url=`` the level sensor's port (the two USB ports swapped). Before: "RigTimeout: no reply
    from fakerig://fake/level within 0 s" (the wait was 2 s); now the wait, the last line and the likely slip."""
    world.reset()
    ctl = GrblController(world.url("level"), timeout=0.3)
    with pytest.raises(RigTimeout, match=r"^no start-up banner from fakerig://testrig/level within 0\.3 s of a soft "
                                         r"reset; it sent \d+ line\(s\) that are not GRBL's, the last "
                                         r"'L=\d+\.\d{3} mm': is rig\.controller\.url the controller's port "
                                         r"\(not the sensor's\)\?$"):
        ctl.connect()
    ctl.close()


def test_an_unknown_wait_mode_is_refused_naming_its_option():
    """``scan.py rig.controller.wait=foo`` said "wait must be 'dwell' or 'poll'", without the option's path."""
    with pytest.raises(ValueError, match=r"^rig.controller.wait must be 'dwell' or 'poll', got 'foo'$"):
        GrblController("loop://", wait="foo")
