"""Marlin 2.x dialect: pure line parsers and the :class:`MarlinController` driver.

Protocol facts (Marlin 2.x)
---------------------------
* Every line is acknowledged by ``ok`` (optionally ``ok N.. P.. B..`` with ADVANCED_OK).
* While a long command runs (``G28``, ``M400``) the firmware sends ``echo:busy: processing``
  every couple of seconds (HOST_KEEPALIVE): the host must keep waiting.
* Lines may carry a line number and checksum, ``N12 G1 Z5*57`` (checksum = XOR of every byte
  before ``*``); ``M110 N0`` sets the expected number. A bad line is answered by
  ``Error:checksum mismatch, Last Line: 11`` / ``Error:Line Number is not Last Line Number+1``,
  then ``Resend: 12`` and ``ok``: the host resends from that line.
* ``M114`` reports ``X:0.00 Y:0.00 Z:10.00 E:0.00 Count X:0 Y:0 Z:4000``: the logical position (what the
  moves commanded, ``G92`` / ``M206`` offsets included), then, after ``Count``, the position in steps in the
  machine's own frame (Marlin 2.x: the planner's, ``report_current_position_projected``; with ``M114_LEGACY``
  the steppers' counts). ``M92`` with no arguments answers ``  M92 X80.00 Y80.00 Z400.00 E500.00`` (steps per
  unit; older 2.0 versions print ``echo:`` first, Marlin 1.x only ``ok``), ``M503`` the same line after
  ``echo:``. ``M400`` returns when every move has finished; ``M410`` quick-stops; ``G28`` homes.
* A move cut short by an endstop (a crash, or a stall that stall detection wired as an endstop caught, with
  endstops on during moves) is reported by ``echo:endstops hit:  Z:-5.00``; the planner keeps the target.
* ``start`` is printed after a reset; ``Error:Printer halted. kill() called!`` means halted.
"""

from __future__ import annotations

import re
import time
import logging
from collections.abc import Iterable
from dataclasses import dataclass

from dipnet.core.flags import checked_flag
from dipnet.rig.controller import (AlarmError, Axis, Controller, ControllerError, Position, PositionMismatch,
                                   PositionUnknown, ResetError, RigTimeout, require_link)

log = logging.getLogger(__name__)

_RESEND = re.compile(r"^(?:Resend:|rs)\s*N?(?P<n>\d+)", re.IGNORECASE)
_AXIS = re.compile(r"(?P<axis>[A-Z]):\s*(?P<value>[-+]?\d+(?:\.\d*)?)")
_FATAL = ("halted", "kill()", "stopped")
_M92 = re.compile(r"\bM92((?:\s+[A-Z][-+]?\d+(?:\.\d*)?)+)\s*$")
_WORD = re.compile(r"(?P<axis>[A-Z])(?P<value>[-+]?\d+(?:\.\d*)?)")
#: Decimals of Marlin's ``M92`` report: the steps per unit it prints are within half of their last digit.
M92_ROUNDING = 0.005


@dataclass(frozen=True)
class MarlinLine:
    """One classified line from a Marlin controller.

    Attributes:
        kind: ``"ok" | "busy" | "resend" | "error" | "fatal" | "start" | "position" | "echo" | "other"``.
        text: the line as received (stripped).
        number: the line number of a ``Resend``.
        payload: the message text after ``Error:`` / ``echo:``.
    """

    kind: str
    text: str
    number: int | None = None
    payload: str = ""


def checksum(text: str) -> int:
    """Marlin's line checksum: XOR of every byte of ``text`` (the part before ``*``)."""
    value = 0
    for byte in text.encode("ascii"):
        value ^= byte
    return value


def numbered(n: int, command: str) -> str:
    """``N<n> <command>*<checksum>`` (pure)."""
    text = f"N{n} {command}"
    return f"{text}*{checksum(text)}"


def classify(line: str) -> MarlinLine:
    """Classify one received line (pure)."""
    text = line.strip()
    if text == "ok" or text.startswith("ok ") or text.startswith("ok\t"):
        return MarlinLine("ok", text)
    low = text.lower()
    if low.startswith("echo:busy") or low.startswith("busy:"):
        return MarlinLine("busy", text)
    m = _RESEND.match(text)
    if m:
        return MarlinLine("resend", text, number=int(m["n"]))
    if low.startswith("error:") or text.startswith("!!"):
        payload = text.split(":", 1)[1] if ":" in text else text
        return MarlinLine("fatal" if any(w in low for w in _FATAL) or text.startswith("!!") else "error",
                          text, payload=payload.strip())
    if text == "start":
        return MarlinLine("start", text)
    if low.startswith("echo:"):
        return MarlinLine("echo", text, payload=text[5:].strip())
    if parse_position(text):
        return MarlinLine("position", text)
    return MarlinLine("other", text)


def no_ok(line: str, url: str, limit: float, received: list[str]) -> str:
    """The message of a command ``line`` that got no ``ok`` within ``limit`` s, naming the last of the other
    lines ``received`` meanwhile: a device that answers with lines of its own (pure)."""
    message = f"no 'ok' to {line!r} from {url} within {limit:g} s"
    if not received:
        return message
    return (f"{message}; it sent {len(received)} other line(s), the last {received[-1]!r}: is rig.controller.url "
            f"the controller's port (not the sensor's)?")


def parse_position(line: str) -> dict[str, float]:
    """Axis positions of an ``M114`` reply, ``{"X": 0.0, ..., "E": 0.0}`` (the part before
    ``Count``, i.e. the planner's logical position); ``{}`` if the line is not one (pure)."""
    head = line.split("Count", 1)[0]
    if not re.match(r"^\s*[A-Z]:", head):
        return {}
    return {m["axis"]: float(m["value"]) for m in _AXIS.finditer(head)}


def parse_counts(line: str) -> dict[str, int]:
    """Step counts of an ``M114`` reply, the part after ``Count``: ``{"X": 0, "Y": 0, "Z": 4000}``; ``{}`` if the
    line is not a position report or has no counts (pure)."""
    if "Count" not in line or not parse_position(line):
        return {}
    return {m["axis"]: round(float(m["value"])) for m in _AXIS.finditer(line.split("Count", 1)[1])}


def parse_steps_per_unit(lines: Iterable[str]) -> dict[str, float]:
    """Steps per unit (per mm, or per degree of a rotary axis) of the first ``M92`` report among ``lines``
    (``M92``'s own ``  M92 X80.00 Y80.00 Z400.00 E500.00``, or ``M503``'s, after ``echo:``), by axis letter;
    ``{}`` if none (pure)."""
    for line in lines:
        m = _M92.search(line)
        if m:
            return {w["axis"]: float(w["value"]) for w in _WORD.finditer(m[1])}
    return {}


class MarlinController(Controller):
    """Marlin 2.x driver (see the module docstring).

    Args (beyond :class:`~dipnet.rig.controller.Controller`'s):
        line_numbers: send ``N.. *checksum`` lines and honour ``Resend:``.
        max_resends: give up (``ControllerError``) after this many resends of one line.
        home_command: the homing line (``G28``, or ``G28 Z`` to home the lowering axis only).
        startup_s: time to wait for the ``start`` banner after opening (boards reset on open);
            0 to skip.
    """

    dialect = "marlin"

    def __init__(self, url: str, axes=None, *, line_numbers: bool = True, max_resends: int = 3,
                 home_command: str = "G28", startup_s: float = 0.0, **options) -> None:
        super().__init__(url, axes, **options)
        line_numbers = checked_flag("rig.controller.line_numbers", line_numbers)  # bool("no") is true
        self.line_numbers = line_numbers
        self.max_resends = int(max_resends)
        self.home_command = home_command
        self.startup_s = float(startup_s)
        self._next = 1
        self._sent: dict[int, str] = {}
        self.resends = 0
        self.steps_per_unit: dict[str, float] = {}  # M92, read at connect
        self._heard = 0  # messages already searched for endstop hits
        self._unchecked_said = False

    def identity(self) -> dict:
        return {**super().identity(), "line_numbers": self.line_numbers, "steps_per_unit": self.steps_per_unit}

    # ------------------------------------------------------------------ lines
    def _frame(self, line: str) -> str:
        if not self.line_numbers:
            return line
        n = self._next
        self._next += 1
        self._sent = {k: v for k, v in self._sent.items() if k > n - 16}
        self._sent[n] = numbered(n, line)
        return self._sent[n]

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        link = require_link(self)
        limit = self.timeout if timeout is None else float(timeout)
        link.write_line(self._frame(line))
        received, error, resend, tries = [], None, None, 0
        deadline = time.monotonic() + limit  # other lines do not extend it: a port that streams is not waited forever
        while True:
            try:
                reply = classify(link.read_line(max(deadline - time.monotonic(), 0.0)))
            except RigTimeout:
                raise RigTimeout(no_ok(line, self.url, limit, received)) from None
            if reply.kind == "busy":
                deadline = time.monotonic() + limit  # keep-alive: the firmware is working, the limit restarts
                continue
            if reply.kind == "start":
                self.lose_position("the controller was reset (Marlin forgets its position)")
                self._next, self._sent = 1, {}
                raise ResetError(f"controller was reset unexpectedly ('start' while waiting for {line!r})")
            if reply.kind == "fatal":
                self.lose_position(f"the controller halted ({reply.payload})")
                raise AlarmError(f"controller halted: {reply.payload}")
            if reply.kind == "error":
                error = reply.payload
            elif reply.kind == "resend":
                resend = reply.number
            elif reply.kind == "ok":
                if resend is not None:
                    tries += 1
                    if resend not in self._sent or tries > self.max_resends:
                        raise ControllerError(f"controller asks to resend line {resend} of {line!r} "
                                              f"({error or 'no reason given'}); giving up")
                    for n in sorted(k for k in self._sent if k >= resend):
                        link.write_line(self._sent[n])
                    error, resend = None, None
                    self.resends += 1
                    continue
                if error is not None:
                    raise ControllerError(f"controller rejected {line!r}: {error}")
                return received
            else:
                if reply.kind in ("echo", "other") and reply.text:
                    self.messages.append(reply.text)
                received.append(reply.text)

    # ------------------------------------------------------------------ interface
    def _handshake(self) -> None:
        link = require_link(self)
        if self.startup_s > 0:
            deadline = time.monotonic() + self.startup_s
            try:
                while classify(link.read_line(max(deadline - time.monotonic(), 1e-3))).kind != "start":
                    pass
            except RigTimeout:
                pass
        link.discard_input()
        self._reset_numbers()
        self.absolute_mm()
        self.steps_per_unit = self._read_steps_per_unit()
        self._heard, self._unchecked_said = len(self.messages), False

    def _read_steps_per_unit(self) -> dict[str, float]:
        """``M92`` (no arguments), else ``M503``: the steps per unit, ``{}`` when the firmware reports neither
        (``M92`` answering only ``ok`` in Marlin 1.x, ``M503`` compiled out by ``DISABLE_M503``)."""
        for line in ("M92", "M503"):
            steps = parse_steps_per_unit(self.command(line))
            if steps:
                return steps
        return {}

    def _reset_numbers(self) -> None:
        if self.line_numbers:
            self._next, self._sent = 0, {}
            self.command("M110 N0")  # this line itself is N0; the next expected is N1

    def settle(self) -> Position:
        """See :meth:`Controller.settle`. A halt (``kill()`` / "Printer stopped") or a reset
        loses the position: :class:`PositionUnknown` unless :meth:`home` ran since. No ``M410``
        here: a quick stop without deceleration loses steps."""
        self.messages += require_link(self).drain(quiet_s=0.05, limit_s=0.5)
        for _ in range(3):
            if self.position_lost is not None:
                raise PositionUnknown(self.position_lost)
            try:
                self._reset_numbers()
                self.command("M400", timeout=self.move_timeout)
                position = self.position()
                self.absolute_mm()
                return position
            except (AlarmError, ResetError):
                continue
        raise PositionUnknown(self.position_lost or "the controller did not settle after 3 attempts")

    def home(self) -> None:
        if self.position_lost is not None:
            self._reset_numbers()
            self.command("M999")  # restart after "Printer stopped due to errors" (harmless otherwise)
        self.command(self.home_command, timeout=self.home_timeout)
        self.position_lost, self._target = None, {}
        self.absolute_mm()
        self._heard = len(self.messages)

    def wait_idle(self, timeout: float | None = None) -> None:
        self.command("M400", timeout=self.move_timeout if timeout is None else timeout)

    def position(self) -> Position:
        return self.axes.rig_position(parse_position(self._report()))

    def _report(self) -> str:
        """The position line of an ``M114`` reply."""
        for text in self.command("M114"):
            if parse_position(text):
                return text
        raise ControllerError("M114 gave no position line")

    def check_arrived(self) -> None:
        """See :meth:`Controller.check_arrived`. An ``endstops hit`` message since the last check (a crash, or a
        stall that stall detection caught: the axis stopped short, while the planner keeps the target) loses the
        position. Then the ``M114`` counts against the commanded rig values, per axis within one step plus the
        rounding of the printed steps per unit (``M92``, read at connect), modulo
        :attr:`~dipnet.rig.controller.Axis.wrap` for a free axis. The counts are in the machine's frame and the
        moves in the logical one: a work offset (``G92``), a home offset (``M206``), inch moves (``G20``), a move
        clamped by a software endstop, or steps per unit changed since connect put the machine elsewhere.
        A firmware that reports no steps per unit or no counts is not checked (a warning says so, once per
        connection). Steps lost without the firmware noticing (no stall detection) are counted all the same:
        only an encoder would see them. Cartesian kinematics only (a CoreXY's or delta's counts are per motor)."""
        counts = parse_counts(self._report())
        self._check_endstop_hits()
        off, unknown = [], []
        for name, commanded in self._target.items():
            axis = getattr(self.axes, name)
            letter, steps = axis.letter.upper(), self.steps_per_unit.get(axis.letter.upper())
            if not steps or letter not in counts:
                unknown.append(letter)
            elif not self._counted_at(axis, counts[letter], steps, commanded):
                unit = "mm" if name == "lower" else "deg"
                here = round(axis.from_machine(counts[letter] / steps), 3) + 0.0  # no "-0.000"
                off.append(f"{name} {here:.3f} {unit} (commanded {commanded:g}, {letter} count {counts[letter]} at "
                           f"{steps:g} steps/unit)")
        if unknown and not self._unchecked_said:
            self._unchecked_said = True
            log.warning("not checking that the machine arrives where the scan sends it: the controller reports %s",
                        "no steps per unit (M92 answers only 'ok' in Marlin 1.x; M503 may be compiled out)"
                        if not self.steps_per_unit else f"no steps per unit (M92) or no step count (M114 'Count') for "
                        f"axis {', '.join(unknown)}")
        if off:
            raise PositionMismatch(
                f"idle after the move, the controller counts {', '.join(off)}: the machine is not where the scan sent "
                f"it, and no reading is recorded there. Marlin moves in logical coordinates and counts steps in its "
                f"own: clear a work offset (G92; homing with G28 clears it) and a home offset (M206 with zeros, then "
                f"M500), keep mm (G21), keep the moves inside the software endstops (M211), check that the steps per "
                f"unit (M92) did not change since connect and rig.controller.axes (scale, sign, offset)")

    def _check_endstop_hits(self) -> None:
        """Raise :class:`PositionMismatch`, and lose the position, if an ``endstops hit`` message came since the
        last check."""
        hits = [text for text in self.messages[self._heard:] if "endstops hit" in text.lower()]
        self._heard = len(self.messages)
        if hits:
            self.lose_position(f"the controller reported {hits[-1]!r} during a move")
            raise PositionMismatch(
                f"the controller reported {hits[-1]!r} during the move: an axis stopped short (a crash, a stall or a "
                f"driver fault; steps were lost) while the controller counts the full move, and no reading is recorded "
                f"there. Free the axis, check the driver and its current, then home (home=true)")

    @staticmethod
    def _counted_at(axis: Axis, count: int, steps: float, commanded: float) -> bool:
        """Whether ``count`` steps at ``steps`` per machine unit (as printed, to :data:`M92_ROUNDING`) stand at rig
        value ``commanded`` of ``axis``: within one step plus the printing's rounding, modulo a free axis's wrap."""
        tolerance = (1.0 + M92_ROUNDING * abs(count) / steps) / steps / axis.scale  # rig units
        return abs(axis.nearest(axis.from_machine(count / steps), commanded) - commanded) <= tolerance

    def stop(self) -> None:
        """Wait for the queue to empty (``M400``); ``M410`` would stop without deceleration and lose steps."""
        self.command("M400", timeout=self.move_timeout)
