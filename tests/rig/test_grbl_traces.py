"""The GRBL driver against the real firmware's recorded replies (tests/data/grbl-traces, see its README).

Each test replays one recorded scenario (:mod:`grbl_replay`): the driver must send what the
recording expects up to the fault, and then the right thing, concluding only what the
firmware's replies confirm.
"""

from __future__ import annotations

import pytest

from dipnet.core.rawscan import ScanHeader
from dipnet.rig.controller import (AlarmError, AxisMap, ControllerError, LineChannel, MotionHeld, PositionUnknown,
                                   RigDisconnected, RigTimeout)
from dipnet.rig.grbl import GrblController
from dipnet.rig.grbl_dialect import check_settings, parse_status
from dipnet.rig.runner import RigConfigError, ScanAborted, ScanPlan, ScanRunner, value_ranges
from dipnet.rig.sensors import Reading
from grbl_replay import ReplayPort, asked_first, read_trace, recorded_replies

AXES_3 = {"tilt": {"letter": "X"}, "spin": {"letter": "Y"}}  # how the traces were recorded
SETTINGS = recorded_replies(read_trace("t1.log")[3])  # the board's replies to $$ and $I
AFTER_RESET = read_trace("t3b2.log")[0]  # what GRBL answered after the reset that ALARM:2 asks for
#: The driver's G21 after each G90, which the recordings predate: answered as the firmware answers every accepted
#: line, with ``ok`` (its modal state already held G21: the ``$G`` reply in t1.log).
UNITS_MM = {b"G21\n": [b"ok\r\n"]}


def replay(script, answers=None, axes=None, **options) -> tuple[GrblController, ReplayPort]:
    """The driver connected to a replay of ``script``; a recorded session that opens with the old
    driver's soft reset gets the ``?`` the driver now asks first (:func:`asked_first`)."""
    script = asked_first(script) if script[:1] == [(">>", b"\x18")] else script
    port = ReplayPort(script, answers, extras={b"$$\n": SETTINGS[b"$$\n"], b"$I\n": SETTINGS[b"$I\n"], **UNITS_MM})
    ctl = GrblController("replay://", axes or AXES_3, status_axes="XYZ", **{"timeout": 0.2, "move_timeout": 0.5,
                                                                             **options})
    ctl.attach(LineChannel(port))
    return ctl, port


def replay_moves(ctl: GrblController, port: ReplayPort) -> None:
    """Issue the recorded G0 moves through the driver (each followed by wait_idle)."""
    for direction, data in port.script[port._cursor:]:
        if direction == ">>" and data.startswith(b"G0 "):
            words = {w[0]: float(w[1:]) for w in data.decode().split()[1:]}
            ctl.move_to(lower_mm=-words["Z"] if "Z" in words else None, tilt_deg=words.get("X"),
                        spin_deg=words.get("Y"))
            ctl.wait_idle()


def test_t1_settings_are_read_and_checked():
    ctl, port = replay(read_trace("t1.log")[3])
    assert ctl.version == "1.1h" and "[VER:1.1h.20190830:]" in ctl.build_info
    assert ctl.settings[10] == 1 and ctl.settings[22] == 0 and ctl.settings[130] == 200.0
    problems = ctl.check_board(True, {"lower": (0.0, 40.0), "tilt": (0.0, 90.0), "spin": (0.0, 300.0)})
    assert len(problems) == 1 and "$22=0" in problems[0]
    assert ctl.check_board(False, {"lower": (0.0, 40.0)}) == []
    with pytest.raises(ControllerError, match="status_axes='XYZAB'.*grbl_3axis"):
        GrblController("replay://", status_axes="XYZAB", timeout=0.2).attach(
            LineChannel(ReplayPort(asked_first(read_trace("t1.log")[3]))))


def test_t2b_normal_path_sends_what_the_firmware_expects():
    ctl, port = replay(read_trace("t2b.log")[0])
    replay_moves(ctl, port)
    assert port.diverged_at is None and port._cursor == len(port.script)  # every recorded chunk, in order
    assert not ctl.unacked and ctl.axes.rig_position(ctl.last_status.mpos).lower_mm == 0.0


def test_t3a_errors_are_described():
    ctl, port = replay(read_trace("t3a.log")[0])
    for line, text in (("G99", r"error:20 \(unsupported"), ("G1 Z-1", r"error:22 \(feed rate"),
                       ("$20=1", r"error:10 \(soft limits need homing")):
        with pytest.raises(ControllerError, match=text):
            ctl.command(line)
    with pytest.raises(ControllerError, match=r"homing is disabled on the board \(\$22=0\)"):
        ctl.home()
    assert ctl.position().lower_mm == 0.0 and port.diverged_at is None


def test_t3b_alarm2_gets_the_reset():
    status = recorded_replies(AFTER_RESET)
    idle = b"<Idle|MPos:80.404,84.984,0.000|FS:0,0|Pn:PXYZRHS>\r\n"  # state after $X, as in t3b2
    ctl, port = replay(read_trace("t3b.log")[1], {
        b"\x18": [status[b"\x18"][0]], b"?": [status[b"?"][0], idle], b"$X\n": status[b"$X\n"],
        b"G90\n": [b"ok\r\n"]})
    with pytest.raises(AlarmError, match="ALARM:2"):
        ctl.move_to(lower_mm=0.0)  # the recorded G0 Z0.0000: the soft limit alarms
    assert ctl.needs_reset and ctl.position_lost is None  # ALARM:2 keeps the position
    position = ctl.settle()
    assert port.since_divergence()[0] == b"\x18"  # the reset GRBL asks for, not '?' into the silence
    assert b"$X\n" in port.sent and position.lower_mm == 0.0 and not ctl.unacked


def test_t3d_alarm3_no_unlock_no_motion():
    ctl, port = replay(read_trace("t3d.log")[0])
    with pytest.raises(AlarmError, match="ALARM:3"):
        replay_moves(ctl, port)
    assert ctl.position_lost and "ALARM:3" in ctl.position_lost
    with pytest.raises(PositionUnknown):
        ctl.settle()  # reads back: banner, then <Alarm|...>
    assert ctl.last_status.state == "Alarm"
    assert b"$X\n" not in port.sent and not any(c.startswith(b"G0") for c in port.since_divergence())
    with pytest.raises(PositionUnknown, match="refusing to move"):
        ctl.move_to(lower_mm=0.0)


def test_t3e_resume_after_alarm3_is_refused_although_grbl_reports_idle():
    # after t3d's ALARM:3 and a reset, GRBL ($22=0) answers Idle at the old coordinates: only the
    # runner's position-lost marker (ScanRunner._establish_position -> lose_position) knows better
    ctl, port = replay(read_trace("t3e.log")[0])
    assert ctl.last_status.state == "Idle" and ctl.position_lost is None
    ctl.lose_position("the previous run lost the position (ALARM:3)")
    with pytest.raises(PositionUnknown, match="refusing to move: the previous run lost the position"):
        ctl.move_to(lower_mm=0.0)  # the recorded client sent G0 Z0.0000 here and went on scanning
    assert port.diverged_at is None and not any(c.startswith(b"G0") for c in port.sent)


def test_t3h_hold_reported_at_once_and_late_ok_attributed():
    script = read_trace("t3h.log")[0]
    ctl, port = replay(script)
    with pytest.raises(MotionHeld, match="Hold:0 at lower 22.428 mm"):
        replay_moves(ctl, port)  # the hold lands during the lowering to 40 mm
    assert [line for _, line in ctl.unacked] == ["G4 P0"]  # the dwell is still unanswered
    # the recorded continuation of the old driver: '~', then the lift and its dwell
    port.write(b"~")
    lift = ctl.send("G0 Z0.0000")
    ctl._pump(0.2)  # the one 'ok' that arrives is the held dwell's, not the lift's
    assert ctl.late == ["G4 P0 -> ok"] and [s for s, _ in ctl.unacked] == [lift]
    dwell = ctl.send("G4 P0")
    ctl._pump(0.2)
    assert [s for s, _ in ctl.unacked] == [dwell]  # that 'ok' answers the lift
    st = ctl.status()
    assert st.state == "Idle" and ctl.axes.rig_position(st.mpos).lower_mm == 40.0
    # the lift's dwell is unanswered: the driver does not take this Idle for "lifted"
    with pytest.raises(Exception):
        ctl.wait_for(dwell, "G4 P0", 0.1)


def test_t3h_settle_cancels_the_hold_without_resuming():
    script = read_trace("t3h.log")[0]
    hold = b"<Hold:0|MPos:33.556,0.000,-22.428|FS:0,0|Pn:PXYZRHS>\r\n"
    # GRBL 1.1 interface docs: a reset in a completed hold (Hold:0) keeps the position
    ctl, port = replay(script, {b"?": [hold, b"<Idle|MPos:33.556,0.000,-22.428|FS:0,0>\r\n"],
                                b"\x18": [b"ok\r\n\r\nGrbl 1.1h ['$' for help]\r\n"]})
    with pytest.raises(MotionHeld):
        replay_moves(ctl, port)
    position = ctl.settle()
    assert position.lower_mm == pytest.approx(22.428) and not ctl.unacked and ctl.position_lost is None
    assert b"~" not in port.sent and port.sent[-2:] == [b"\x18", b"?"]


@pytest.mark.parametrize("name,bad", [("t3f.log", b"<Hold:0|MPos:33.556,0.000,-15.000:FS:0,0|Pn:PXYZRHS>\r\n"),
                                      ("t3g.log", b"<Idle|MPos:33.556,0.000,-15.000|FS:0,0|P\n:PXYZRHS>\r\n")])
def test_t3f_t3g_corrupted_and_split_status_lines(name, bad):
    assert bad in b"".join(data for _, data in read_trace(name)[-1])  # as the firmware sent it
    state = bad[1:5].decode()
    good = b"<%s|MPos:33.556,0.000,-15.000|FS:0,0|Pn:PXYZRHS>\r\n" % (b"Hold:0" if state == "Hold" else b"Idle")
    ctl, port = replay([], {b"?": [good, bad, good], b"G90\n": [b"ok\r\n"]}, reset_on_connect=False)
    with pytest.raises(ValueError):
        parse_status(bad.split(b"\n")[0].decode().strip())
    st = ctl.status()  # the broken report is queried again, not raised
    assert st.state == state and ctl.axes.rig_position(st.mpos).lower_mm == 15.0
    assert port.sent[-2:] == [b"?", b"?"]


# ----------------------------------------------------------------------------- second recording (t4*)
class StubSensor:
    """A level sensor that always reads a stable 100 mm (the replays test the controller)."""

    quantity = "level_mm"

    def identity(self) -> dict:
        return {"kind": "StubSensor"}

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read(self) -> Reading:
        return Reading(100.0, "mm", True)


class ReplayGrbl(GrblController):
    """The driver on replayed sessions: each (re)connect attaches the next of ``ports``; with none
    left the port cannot be opened, as while the recorded link was down."""

    def __init__(self, ports: list[ReplayPort], axes: dict, **options) -> None:
        super().__init__("replay://", axes, status_axes="XYZ", timeout=0.2, move_timeout=30.0, **options)
        self.ports = list(ports)

    def connect(self) -> None:
        if not self.ports:
            raise RigDisconnected("cannot open replay://: connection refused (the link is down)")
        self.attach(LineChannel(self.ports.pop(0)))


def replay_runner(session, axes: dict, orientations, tmp_path, **options) -> tuple[ScanRunner, ReplayPort]:
    """A scan of ``orientations`` (stages 0, 10, 20, 30 mm) replayed on one recorded session. The
    runner's extra ``?`` (where the first move starts, for the short way round) is answered as
    the firmware answered the query after the reset."""
    port = ReplayPort(asked_first(session), extras={b"?": recorded_replies(session)[b"?"][:1], **UNITS_MM})
    plan = ScanPlan(orientations, start_mm=0.0, stop_mm=30.0, step_mm=10.0)
    header = ScanHeader(tank_cross_section_mm2=2e4, step_mm=10.0)
    runner = ScanRunner(ReplayGrbl([port], axes), StubSensor(), plan, tmp_path / "scan.jsonl", header,
                        progress=False, fsync=False, **{"home": None, **options})
    return runner, port


AXES_3AXIS = {**AXES_3, "spin": {"letter": "Y", "wrap": 360.0}}  # rig=grbl_3axis, as t4e3 was recorded
T4E3_PLAN = [(30.0, 0.0), (30.0, 10.0)]


def test_t4e3_could_not_lift_writes_the_marker_and_the_resume_waits_for_confirmation(tmp_path):
    first, resume = read_trace("t4e3_powercycle.log")[1:]  # [0]: the simulator's setup
    runner, port = replay_runner(first, AXES_3AXIS, T4E3_PLAN, tmp_path)
    with pytest.raises(ScanAborted) as info:
        runner.run()  # the recorded run: the board's port is gone while the safe stop retries
    ctl, message = runner.controller, str(info.value)
    assert port.dropped and ctl.position_lost.startswith("lost the link to replay://")
    assert ctl.axes.rig_position(ctl.last_status.mpos).lower_mm == pytest.approx(20.456)  # still moving to 30
    assert "COULD NOT LIFT" in message and "lost the link" in message and port.diverged_at is None
    assert "resume with confirm_position=true" in message and "home=true" not in message  # $22=0: cannot home
    assert "run the same command" not in message
    assert "lost the link" in runner.marker.read_text()
    # the same command again (the recorded resume): the restarted board says Idle at 0; nothing moves
    runner, port = replay_runner(resume, AXES_3AXIS, T4E3_PLAN, tmp_path)
    with pytest.raises(ScanAborted, match="previous run lost the position.*nothing had moved.*confirm_position=true"):
        runner.run()
    restarted = runner.controller.last_status
    assert restarted.state == "Idle" and restarted.mpos == {"X": 0.0, "Y": 0.0, "Z": 0.0}  # counts from 0
    assert not any(chunk.startswith(b"G0") for chunk in port.sent) and runner.marker.exists()


def test_t4e2_connect_lets_the_move_finish_before_the_reset():
    first, reconnect = read_trace("t4e2_reconnect_moving.log")[1:3]
    assert recorded_replies(reconnect)[b"\x18"][0].startswith(b"ALARM:3")  # the old driver's reset aborted it
    running = [data for d, data in first if d == "<<" and data.startswith(b"<Run")][-1]  # Z -20.108, to -30
    ended = next(data for d, data in read_trace("t4e3_powercycle.log")[2]
                 if d == "<<" and data.startswith(b"<Idle|MPos:30.000,0.000,-30.000"))  # the same move, completed
    ctl, port = replay([], {b"?": [running, running, ended], b"\x18": recorded_replies(first)[b"\x18"],
                            b"G90\n": [b"ok\r\n"]})
    assert port.sent[:4] == [b"?", b"?", b"?", b"\x18"]  # the reset only once the machine is Idle
    assert ctl.alarm is None and ctl.position_lost is None
    assert ctl.axes.rig_position(ctl.last_status.mpos).lower_mm == 30.0


def test_t4e2_connect_does_not_reset_a_machine_that_keeps_moving():
    running = [data for d, data in read_trace("t4e2_reconnect_moving.log")[1]
               if d == "<<" and data.startswith(b"<Run")][-1]
    port = ReplayPort([], {b"?": [running]})
    with pytest.raises(RigTimeout, match="still moving .* not resetting it"):
        GrblController("replay://", AXES_3, status_axes="XYZ", timeout=0.2, move_timeout=0.3).attach(LineChannel(port))
    assert b"\x18" not in port.sent


AXES_T4D = {"tilt": {"letter": "X", "sign": -1}, "spin": {"letter": "Y", "sign": -1, "wrap": 360.0}}


def test_t4d_soft_limit_check_takes_the_short_way_round(tmp_path):
    first = read_trace("t4d_softlimit_wrap.log")[1]
    assert b"ALARM:2" in recorded_replies(first)[b"G0 X-30.0000 Y165.0000\n"][0]  # spin 10 -> 195 went via Y+
    runner, port = replay_runner(first, AXES_T4D, [(30.0, 10.0), (30.0, 195.0)], tmp_path, home=False,
                                 confirm_position=True)
    with pytest.raises(RigConfigError) as info:
        runner.run()
    message = str(info.value)
    assert "spin to Y -10..165 (the short way round, wrap=360)" in message
    assert "set rig.controller.axes.spin.wrap=null so that spin turns directly (Y -195..-10 fits)" in message
    assert "raise $131" not in message and "same command" not in message  # no travel makes Y 165 fit
    assert not any(chunk.startswith((b"G0", b"$X")) for chunk in port.sent)  # checked before anything moved
    # turning directly, the same moves fit the board's travel
    direct = AxisMap.from_config({**AXES_T4D, "spin": {"letter": "Y", "sign": -1}})
    moves = [{"tilt": 30.0, "spin": 10.0}, {"tilt": 30.0, "spin": 195.0}]
    assert check_settings(runner.controller.settings, "XYZ", direct, False,
                          value_ranges(direct.route(moves, {"tilt": 0.0, "spin": 0.0}))) == []
