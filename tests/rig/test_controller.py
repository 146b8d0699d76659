"""What every controller driver shares (dipnet.rig.controller): axes and the axis map between rig coordinates and
machine words (the short way round included), the line channel's reads, timeouts and lost links."""

from __future__ import annotations

import pytest
import serial

from dipnet.rig.controller import (
    Axis,
    AxisMap,
    ControllerError,
    LineChannel,
    Position,
    RigDisconnected,
    RigTimeout,
    open_port,
)


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


def test_an_axis_converts_rig_values_to_machine_words_and_back():
    axis = Axis("z", scale=2.0, sign=-1, offset=5.0)
    for value in (-12.5, 0.0, 3.25, 100.0):
        assert axis.from_machine(axis.to_machine(value)) == pytest.approx(value)
    assert axis.to_machine(10.0) == -15.0
    for bad, message in (({"letter": "ZZ"}, "one letter"), ({"letter": "1"}, "one letter"),
                         ({"letter": "Z", "sign": 2}, "sign must be"),
                         ({"letter": "Z", "scale": 0.0}, "scale must be a finite positive number"),
                         ({"letter": "B", "wrap": -360.0}, "wrap must be a positive period")):
        with pytest.raises(ValueError, match=message):
            Axis(**bad)


@pytest.mark.parametrize(("axes", "message"), [
    ({"lower": {"offset": float("nan")}}, "rig.controller.axes.lower: axis Z: offset must be a finite number"),
    ({"tilt": {"scale": float("inf")}}, "rig.controller.axes.tilt: axis A: scale must be a finite positive number"),
    ({"tilt": {"scale": 0.0}}, r"rig.controller.axes.tilt: axis A: scale must be .*, got 0.0"),
    ({"spin": {"wrap": float("inf")}}, "rig.controller.axes.spin: axis B: wrap must be a positive period"),
    ({"lower": {"sign": 2}}, r"rig.controller.axes.lower: axis Z: sign must be \+1 or -1, got 2"),
])
def test_an_axis_config_out_of_range_is_refused_naming_its_option(axes, message):
    """scan.py rig.controller.axes.lower.offset=nan was refused only by the scan file's writer: "error: Out of range
    float values are not JSON compliant" (an empty rawscan.jsonl left behind), and scale=inf the same;
    scale=0 said "axis A: sign must be +1/-1 and scale positive", naming neither the option nor the value."""
    with pytest.raises(ValueError, match=message):
        AxisMap.from_config(axes)


def test_a_wrapping_axis_takes_the_short_way_round():
    spin = Axis("B", wrap=360.0)
    assert spin.nearest(350.0, 5.0) == -10.0 and spin.nearest(10.0, 355.0) == 370.0
    assert spin.nearest(180.0, None) == 180.0 and Axis("A").nearest(350.0, 5.0) == 350.0
    axes = AxisMap(spin=spin)
    moves = [{"lower": 0.0, "tilt": 10.0, "spin": 350.0}, {"lower": 20.0, "tilt": None, "spin": 10.0},
             {"lower": None, "tilt": None, "spin": -160.0}]  # 190 deg forward is 170 back
    assert axes.route(moves, {"lower": 0.0, "tilt": 0.0, "spin": 0.0}) == [
        {"lower": 0.0, "tilt": 10.0, "spin": -10.0}, {"lower": 20.0, "tilt": None, "spin": 10.0},
        {"lower": None, "tilt": None, "spin": -160.0}]  # 190 deg forward is 170 back
    assert moves[0]["spin"] == 350.0  # pure: the plan is not changed


def test_a_line_channel_reads_whole_lines_and_times_out_by_name():
    channel = LineChannel(serial.serial_for_url("loop://", timeout=0.01))
    channel.write_line("ok")
    channel.write(b"<Idle|MPos:0,0,0>\r\npart")
    assert channel.read_line(0.5) == "ok" and channel.read_line(0.5) == "<Idle|MPos:0,0,0>"
    with pytest.raises(RigTimeout, match=r"no reply from loop:// within 0.05 s"):
        channel.read_line(0.05)  # half a line is not a line
    channel.write(b"ial\nleft\nover\n")
    assert channel.read_line(0.5) == "partial" and channel.drain(quiet_s=0.05) == ["left", "over"]
    channel.write(b"stale\n")
    channel.discard_input()
    with pytest.raises(RigTimeout):
        channel.read_line(0.05)


def test_a_failed_port_is_a_lost_link_and_tells_its_owner():
    channel = LineChannel(serial.serial_for_url("loop://", timeout=0.01))
    told = []
    channel.on_lost = told.append
    channel.port.close()
    with pytest.raises(RigDisconnected, match="lost the link to loop://"):
        channel.read_line(0.5)
    assert len(told) == 1 and told[0].startswith("lost the link to loop://")
    with pytest.raises(RigDisconnected, match="cannot open fakerig://no-such-rig/grbl"):
        open_port("fakerig://no-such-rig/grbl")


@pytest.mark.parametrize("option, value", [("timeout", -1), ("move_timeout", 0), ("home_timeout", float("nan"))])
def test_a_time_limit_that_cannot_be_waited_is_refused_before_connecting(option, value):
    """Before: ``scan.py rig.controller.timeout=-1`` connected and stopped with exit 3, "RigTimeout: no reply from
    fakerig://fake/grbl within 0 s ... run the same command again to resume": a config slip blamed on the rig."""
    from dipnet.rig.grbl import GrblController

    with pytest.raises(ValueError, match=rf"^rig\.controller\.{option} must be a positive number of seconds "
                                         rf"\(a time limit\), got {value!r}$"):
        GrblController("fakerig://nowhere/grbl", **{option: value})


@pytest.mark.parametrize("feed", [0, -100.0, float("inf")])
def test_a_feed_rate_that_cannot_move_is_refused_before_connecting(feed):
    """Before: ``scan.py rig.controller.feed=0`` sent ``G1 ... F0`` to the board (the fake rig moved anyway)."""
    from dipnet.rig.grbl import GrblController

    with pytest.raises(ValueError, match=rf"^rig\.controller\.feed must be a positive feed rate .*got {feed!r}"):
        GrblController("fakerig://nowhere/grbl", feed=feed)
    assert GrblController("fakerig://nowhere/grbl", feed=500).feed == 500
