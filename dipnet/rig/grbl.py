"""GRBL 1.1 driver: :class:`GrblController` (the dialect: parsers and facts, :mod:`dipnet.rig.grbl_dialect`)."""

from __future__ import annotations

import logging
import time
from collections import deque

from dipnet.rig.controller import (AlarmError, Controller, ControllerError, MotionHeld, Position, PositionMismatch,
                                   PositionUnknown, ResetError, RigTimeout, require_link)
from dipnet.rig.grbl_dialect import (FEED_HOLD, POSITION_LOST_ALARMS, RESET_ALARMS, SOFT_RESET, STATUS_QUERY,
                                      AxisCountError, GrblLine, GrblStatus, check_settings, classify, describe,
                                      in_motion, parse_status, read_settings)

log = logging.getLogger(__name__)

class GrblController(Controller):
    """GRBL 1.1 driver (see the module docstring for the protocol).

    Every line sent is queued in :attr:`unacked` until its own ``ok`` / ``error:N`` arrives
    (GRBL answers lines strictly in order), so a reply that arrives after its command timed
    out is attributed to that command and never taken by a later one; ``?`` queries are
    counted the same way, so a status report is never older than the query it answers. A soft
    reset (banner) empties both queues, as it empties GRBL's buffers.

    Args (beyond :class:`~dipnet.rig.controller.Controller`'s):
        status_axes: the letters of the coordinates in status reports, in order.
        wait: ``"dwell"`` (``G4 P0``, polling ``?`` meanwhile) or ``"poll"`` (``?`` until ``Idle``).
        poll_s: interval between status polls (s).
        reset_on_connect: send a soft reset on connect and wait for the banner.
        status_retries: re-queries of a corrupted or split status report before giving up.
    """

    dialect = "grbl"

    def __init__(self, url: str, axes=None, *, status_axes: str = "XYZAB", wait: str = "dwell",
                 poll_s: float = 0.02, reset_on_connect: bool = True, status_retries: int = 3, **options) -> None:
        super().__init__(url, axes, **options)
        if wait not in ("dwell", "poll"):
            raise ValueError(f"rig.controller.wait must be 'dwell' or 'poll', got {wait!r}")
        self.status_axes = status_axes.upper()
        self.wait = wait
        self.poll_s = float(poll_s)
        self.reset_on_connect = reset_on_connect
        self.status_retries = int(status_retries)
        self.version: str | None = None
        self.settings: dict[int, float] = {}
        self.build_info: list[str] = []
        self.last_status: GrblStatus | None = None
        self.alarm: int | None = None  # last alarm code seen, until a reset / unlock / homing clears it
        self.needs_reset = False  # GRBL asked for a reset ([MSG:Reset to continue])
        self.unacked: deque[tuple[int, str]] = deque()
        self.late: list[str] = []  # replies that arrived after their command had given up
        self._seq = 0
        self._answers: dict[int, GrblLine] = {}
        self._abandoned: set[int] = set()
        self._queries = 0  # '?' sent and not yet answered
        self._expect_banner = False
        self._reports = 0  # status reports received (valid or not)

    def identity(self) -> dict:
        return {**super().identity(), "firmware": self.version, "build": self.build_info,
                "status_axes": self.status_axes}

    # ------------------------------------------------------------------ reading
    def _pump(self, timeout: float, collect: list[str] | None = None) -> GrblLine:
        """Read and account for one line: ``ok`` / ``error`` answer the oldest unacknowledged
        line, status reports answer the oldest ``?``; pushed alarms and unexpected banners raise
        after the state is recorded."""
        reply = classify(require_link(self).read_line(timeout))
        if reply.kind in ("ok", "error"):
            if not self.unacked:
                self.late.append(reply.text)
                log.warning("GRBL sent %r with no command outstanding", reply.text)
                return reply
            seq, line = self.unacked.popleft()
            if seq in self._abandoned:
                self._abandoned.discard(seq)
                self.late.append(f"{line} -> {reply.text}")
                log.warning("late reply %r to %r (its wait had timed out)", reply.text, line)
            else:
                self._answers[seq] = reply
            return reply
        if reply.text.startswith("<"):
            self._queries = max(0, self._queries - 1)
            self._reports += 1
            try:
                self.last_status = parse_status(reply.text, self.status_axes)
            except AxisCountError as exc:
                raise ControllerError(f"the board's status reports do not fit status_axes={self.status_axes!r} "
                                      f"({exc}): set rig.controller.status_axes to one letter per reported "
                                      f"coordinate (a stock GRBL has 3 axes: use rig=grbl_3axis)") from None
            except ValueError as exc:
                self.last_status = None
                log.warning("corrupted status report %r (%s)", reply.text, exc)
            return reply
        if reply.kind == "alarm":
            self.alarm = reply.code
            self.needs_reset = self.needs_reset or reply.code in RESET_ALARMS
            if reply.code in POSITION_LOST_ALARMS:
                self.lose_position(f"the controller raised {describe('alarm', reply.code)}")
            raise AlarmError(f"controller {describe('alarm', reply.code)}", reply.code)
        if reply.kind == "banner":
            self.version = reply.payload
            expected, self._expect_banner = self._expect_banner, False
            self._after_reset()
            if expected:
                raise ResetError("controller reset (as requested)")
            self.lose_position("the controller was reset unexpectedly (a power glitch, or another program): "
                               "its position is unknown")
            raise ResetError(f"controller was reset unexpectedly (banner {reply.text!r})")
        if reply.text:
            self.messages.append(reply.text)
            if collect is not None:
                collect.append(reply.text)
            if reply.text == "[MSG:Reset to continue]":
                self.needs_reset = True
        return reply

    def _after_reset(self) -> None:
        """GRBL empties its buffers on a reset: nothing sent before will be answered."""
        self.unacked.clear()
        self._abandoned.clear()
        self._queries = 0
        self.needs_reset = False
        self._target = {}

    # ------------------------------------------------------------------ lines
    def send(self, line: str) -> int:
        """Send one line without waiting; returns its sequence number (see :meth:`wait_for`)."""
        self._seq += 1
        self.unacked.append((self._seq, line))
        require_link(self).write_line(line)
        return self._seq

    def wait_for(self, seq: int, line: str, timeout: float, collect: list[str] | None = None) -> None:
        """Wait for the reply to line ``seq``; earlier late replies are accounted for on the way.
        On a timeout the line stays queued, so its late reply cannot be taken by a later one."""
        deadline = time.monotonic() + timeout
        try:
            while seq not in self._answers:
                if not any(s == seq for s, _ in self.unacked):
                    raise ResetError(f"controller was reset before it answered {line!r}")
                self._pump(max(deadline - time.monotonic(), 0.0), collect)
        except RigTimeout:
            self._abandoned.add(seq)
            raise RigTimeout(f"no reply to {line!r} from {self.url} within {timeout:g} s") from None
        reply = self._answers.pop(seq)
        if reply.kind == "error":
            raise ControllerError(f"controller rejected {line!r}: {describe('error', reply.code)}", reply.code)

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        received: list[str] = []
        self.wait_for(self.send(line), line, self.timeout if timeout is None else float(timeout), received)
        return received

    def status(self) -> GrblStatus:
        """Send ``?`` and return the report that answers it. A corrupted or split report is
        re-queried up to ``status_retries`` times, then :class:`ControllerError`."""
        link = require_link(self)
        for _ in range(self.status_retries + 1):
            link.write(STATUS_QUERY)
            self._queries += 1
            deadline = time.monotonic() + self.timeout
            try:
                while self._queries:
                    self._pump(max(deadline - time.monotonic(), 0.0))
            except RigTimeout:
                self._queries = 0  # GRBL is silent: no earlier query will be answered either
                raise RigTimeout(f"no status report from {self.url} within {self.timeout:g} s"
                                 + (" (GRBL waits for a reset)" if self.needs_reset else "")) from None
            if self.last_status is not None:
                return self.last_status
        raise ControllerError(f"{self.status_retries + 1} corrupted status reports in a row from {self.url}")

    def _reset(self) -> None:
        """Soft reset (0x18) and wait for the banner; an ``ALARM:3`` on the way is recorded
        (:meth:`_pump` marks the position lost) and the wait continues."""
        link = require_link(self)
        self._expect_banner = True
        link.write(SOFT_RESET)
        deadline = time.monotonic() + self.timeout
        heard = len(self.messages)
        while True:
            try:
                self._pump(max(deadline - time.monotonic(), 0.0))
            except ResetError:
                return
            except AlarmError:
                continue
            except RigTimeout:
                other = [text for text in self.messages[heard:] if classify(text).kind == "other"]
                hint = (f"; it sent {len(other)} line(s) that are not GRBL's, the last {other[-1]!r}: is "
                        f"rig.controller.url the controller's port (not the sensor's)?") if other else ""
                raise RigTimeout(f"no start-up banner from {self.url} within {self.timeout:g} s of a soft reset"
                                 + hint) from None

    # ------------------------------------------------------------------ connect
    def _handshake(self) -> None:
        """Ask ``?`` first: a machine still moving (a move sent before the link was lost, or by a
        previous run) is let finish, since a reset in motion loses the position (``ALARM:3``);
        then reset (``reset_on_connect``, or when GRBL is silent waiting for one)."""
        link = require_link(self)
        self._after_reset()
        link.discard_input()
        current = self._connect_status()
        if current is not None and in_motion(current):
            current = self._wait_stopped(current)
        if current is None or self.reset_on_connect:
            self._reset()
            current = self.status()
        state = current.state
        if state == "Alarm":
            self.lose_position("the controller is in the alarm state (not homed since power-up, or after an "
                               "alarm that lost the position)")
        self.settings = read_settings(self.command("$$"))
        self.build_info = self.command("$I")
        if state != "Alarm":
            self.absolute_mm()

    def _connect_status(self) -> GrblStatus | None:
        """The first status report after the port opened, or ``None`` if GRBL is silent (after
        ``ALARM:1``/``ALARM:2`` it waits for a reset). A banner on the way (the board started as
        the port opened) is expected here."""
        for _ in range(2):
            self._expect_banner = True
            try:
                return self.status()
            except ResetError:
                continue  # the start-up banner: ask again
            except RigTimeout:
                return None
            finally:
                self._expect_banner = False
        return None

    def _wait_stopped(self, st: GrblStatus) -> GrblStatus:
        """Poll until the machine no longer moves (at most ``move_timeout``, ``home_timeout``
        while homing); raises :class:`RigTimeout` instead of resetting a moving machine."""
        limit = self.home_timeout if st.state == "Home" else self.move_timeout
        deadline = time.monotonic() + limit
        log.warning("GRBL reports %s at connect: waiting up to %g s for the motion to end", st.state, limit)
        while in_motion(st):
            if time.monotonic() > deadline:
                raise RigTimeout(f"the machine is still moving ({st.state} at {self._where(st)}) {limit:g} s after "
                                 f"connecting: not resetting it (a reset in motion loses the position)")
            time.sleep(self.poll_s)
            st = self.status()
        return st

    def can_home(self) -> bool:
        return bool(self.settings.get(22, 1))

    def check_board(self, home: bool, targets: dict[str, tuple[float, float]],
                    direct: dict[str, tuple[float, float]] | None = None) -> list[str]:
        return check_settings(self.settings, self.status_axes, self.axes, home, targets, direct)

    # ------------------------------------------------------------------ interface
    def home(self) -> None:
        try:
            self.command("$H", timeout=self.home_timeout)
        except ControllerError as exc:
            if exc.code == 5:
                raise ControllerError("homing is disabled on the board ($22=0): enable it ($22=1, with limit "
                                      "switches) or scan with home=false", 5) from None
            raise
        self.alarm, self.position_lost, self._target = None, None, {}
        self.absolute_mm()
        self.wait_idle()

    def unlock(self) -> None:
        """``$X``: leave the alarm state without homing (only when the position is trusted)."""
        if self.position_lost is not None:
            raise PositionUnknown(f"refusing to unlock ($X) without homing: {self.position_lost}")
        self.command("$X")
        self.alarm = None
        self.absolute_mm()

    def _check_state(self, st: GrblStatus) -> None:
        if st.state in ("Hold", "Door"):
            raise MotionHeld(f"controller reports {st.state}:{st.substate} at {self._where(st)} "
                             f"({'feed hold' if st.state == 'Hold' else 'safety door open'})")
        if st.state == "Alarm":
            raise AlarmError(f"controller is in the alarm state at {self._where(st)}", self.alarm)

    def _where(self, st: GrblStatus) -> str:
        if st.mpos is None:
            return "an unreported position"
        try:
            p = self.axes.rig_position(st.mpos)
        except ControllerError:
            return f"MPos {st.fields.get('MPos')}"
        return f"lower {p.lower_mm:.3f} mm, tilt {p.tilt_deg:.3f} deg, spin {p.spin_deg:.3f} deg"

    def wait_idle(self, timeout: float | None = None) -> None:
        """Wait until the moves finished: ``G4 P0`` is acknowledged (dwell mode) and ``?`` says
        ``Idle``. The state is polled meanwhile, so a feed hold or door raises
        :class:`MotionHeld` at once instead of being waited out."""
        limit = self.move_timeout if timeout is None else float(timeout)
        deadline = time.monotonic() + limit
        seq = self.send("G4 P0") if self.wait == "dwell" else None
        interval = max(self.poll_s, 0.05)
        try:
            while True:
                if seq is not None:
                    try:
                        self.wait_for(seq, "G4 P0", min(interval, max(deadline - time.monotonic(), 0.0)))
                        seq = None
                    except RigTimeout:
                        self._abandoned.discard(seq)  # still ours: keep waiting for it below
                st = self.status()
                if seq is None and st.state == "Idle":
                    return
                self._check_state(st)
                if time.monotonic() > deadline:
                    raise RigTimeout(f"the move did not finish within {limit:g} s (state {st.state})")
                if seq is None:
                    time.sleep(self.poll_s)
        finally:
            if seq is not None and self._answers.pop(seq, None) is None:
                self._abandoned.add(seq)  # given up: its reply, when it comes, is accounted as late

    def check_arrived(self) -> None:
        """See :meth:`Controller.check_arrived`: the ``Idle`` report that ended :meth:`wait_idle` against the
        commanded rig values, per axis within one step (``1 / $10N`` machine units, as read at connect; 0.01 when
        unknown) plus the report's rounding, modulo :attr:`~dipnet.rig.controller.Axis.wrap` for a free axis.
        GRBL moves to ``G0`` targets in work coordinates but reports machine ones (``MPos``): a work offset
        (``G10 L2``/``L20``, ``G92``), inch reports (``$13=1``) or inch moves (``G20``) put the machine
        elsewhere than the scan believes it is."""
        st = self.last_status
        if st is None or st.state != "Idle" or st.mpos is None:
            return
        here = self.axes.rig_position(st.mpos)
        off = []
        for name, reported in (("lower", here.lower_mm), ("tilt", here.tilt_deg), ("spin", here.spin_deg)):
            if name not in self._target:
                continue
            axis, commanded, letter = getattr(self.axes, name), self._target[name], getattr(self.axes, name).letter
            steps = self.settings.get(100 + "XYZABC".find(letter.upper())) if letter.upper() in "XYZABC" else None
            tolerance = ((1.0 / steps if steps else 0.01) + 0.002) / axis.scale  # rig units
            if not abs(axis.nearest(reported, commanded) - commanded) <= tolerance:  # a free axis: modulo its wrap
                unit = "mm" if name == "lower" else "deg"
                off.append(f"{name} {reported:.3f} {unit} (commanded {commanded:g}, {letter.upper()} "
                           f"{st.mpos[letter.upper()]:g} in MPos)")
        if off:
            raise PositionMismatch(
                f"idle after the move, the controller reports {', '.join(off)}: the machine is not where the scan "
                f"sent it, and no reading is recorded there. GRBL moves in work coordinates and reports machine ones: "
                f"clear a work offset (G10 L2 P1 X0 Y0 Z0, with A0 B0 on a 5-axis board, and G92.1; '$#' lists "
                f"them), set $13=0 (reports in mm) and check rig.controller.axes (scale, sign, offset)")

    def position(self) -> Position:
        st = self.status()
        if st.mpos is None:
            raise ControllerError(f"status report has no MPos (or WPos + WCO): set $10=1 ({st.fields})")
        return self.axes.rig_position(st.mpos)

    def settle(self) -> Position:
        """See :meth:`Controller.settle`. GRBL specifics: a pending critical alarm gets the reset
        GRBL asks for; a hold is let finish (``Hold:0``) and then cancelled by a reset, which keeps
        the position; a running move is held first; an alarm is unlocked only when it did not
        lose the position (``ALARM:2``)."""
        self._absorb()
        for _ in range(4):
            try:
                if self.needs_reset:
                    self._reset()
                st = self._status_or_reset()
                if st.state in ("Run", "Jog", "Hold"):
                    self._hold_and_cancel(st)
                    continue
                if st.state == "Door":
                    raise MotionHeld(f"the safety door is open (Door:{st.substate}) at {self._where(st)}: close it")
                if self.position_lost is not None:
                    raise PositionUnknown(self.position_lost)
                if st.state == "Alarm":
                    self.unlock()
                    continue
                if st.mpos is None:
                    raise ControllerError(f"status report has no MPos (or WPos + WCO): set $10=1 ({st.fields})")
                if self.unacked and not self._resynchronise():
                    continue
                return self.axes.rig_position(st.mpos)
            except (AlarmError, ResetError):
                continue
        raise PositionUnknown(self.position_lost or "the controller did not settle after 4 attempts")

    def _absorb(self, quiet_s: float = 0.05, limit_s: float = 0.5) -> None:
        """Account for what a fault left in transit (late replies, alarms, banners: each is
        recorded by :meth:`_pump`) until the line is quiet for ``quiet_s``."""
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            try:
                self._pump(quiet_s)
            except RigTimeout:
                return
            except (AlarmError, ResetError):
                continue

    def _resynchronise(self) -> bool:
        """Idle with lines still unanswered: wait ``timeout`` for their late replies; if some
        never come (a reply was lost), reset GRBL (it is idle, so the position is kept) so
        that no later reply can be mistaken for theirs. Returns whether nothing was reset."""
        deadline = time.monotonic() + self.timeout
        try:
            while self.unacked:
                self._pump(max(deadline - time.monotonic(), 0.0))
            return True
        except RigTimeout:
            log.warning("no reply to %s: resetting the idle controller to resynchronise",
                        ", ".join(repr(line) for _, line in self.unacked))
            self._reset()
            return False

    def _status_or_reset(self) -> GrblStatus:
        """A status report; if GRBL is silent (it waits for a reset after a critical alarm) reset it."""
        try:
            return self.status()
        except RigTimeout:
            log.warning("GRBL does not answer '?': sending the soft reset it waits for")
            self._reset()
            return self.status()

    def _hold_and_cancel(self, st: GrblStatus) -> None:
        """Feed hold, wait until the hold is complete (``Hold:0``), then reset to drop the queued
        moves: GRBL keeps the position when reset in a completed hold."""
        link = require_link(self)
        if st.state != "Hold":
            link.write(FEED_HOLD)
        deadline = time.monotonic() + self.move_timeout
        while not (st.state == "Hold" and st.substate == 0) and st.state not in ("Idle", "Alarm"):
            if time.monotonic() > deadline:
                raise RigTimeout(f"the feed hold did not complete within {self.move_timeout:g} s ({st.state})")
            time.sleep(self.poll_s)
            st = self.status()
        if st.state == "Hold":
            self._reset()

    def stop(self) -> None:
        st = self.status()
        if st.state in ("Run", "Jog", "Hold"):
            self._hold_and_cancel(st)
