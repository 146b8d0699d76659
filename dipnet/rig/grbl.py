"""GRBL 1.1 dialect: pure line parsers and the :class:`GrblController` driver.

Protocol facts (GRBL 1.1 interface docs)
----------------------------------------
* Every line sent is answered by ``ok`` or ``error:N``.
* The controller pushes ``ALARM:N``, ``[MSG:...]`` (and other ``[...]`` feedback) at any time;
  after a (soft) reset it prints its banner ``Grbl 1.1h ['$' for help]``.
* Real-time characters are not lines and get no ``ok``: ``?`` asks for a status report
  ``<State|MPos:x,y,z|FS:f,s|WCO:...>`` (fields vary with ``$10``: parse them by key),
  ``!`` feed hold, ``~`` resume, ``0x18`` soft reset.
* ``$H`` homes, ``$X`` unlocks an alarm. ``G4 P0`` is acknowledged only when the planner
  buffer is empty, i.e. when every earlier move has finished.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field

from dipnet.rig.controller import (AlarmError, Controller, ControllerError, Position, ResetError, RigTimeout,
                                   require_link)

SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
FEED_HOLD = b"!"

#: A few GRBL 1.1 error codes, for readable messages.
ERRORS = {1: "expected command letter", 2: "bad number format", 3: "invalid $ statement",
          8: "not idle", 9: "G-code locked out during alarm or jog state", 15: "travel exceeded (soft limit)",
          20: "unsupported or invalid g-code command", 22: "feed rate not set", 33: "invalid target"}
#: GRBL 1.1 alarm codes.
ALARMS = {1: "hard limit triggered", 2: "soft limit: target exceeds machine travel",
          3: "reset while in motion (position lost)", 4: "probe fail", 5: "probe fail",
          6: "homing fail: reset during homing", 7: "homing fail: door opened", 8: "homing fail: pull-off",
          9: "homing fail: switch not found", 10: "homing fail: second switch not found"}

_BANNER = re.compile(r"^Grbl\s+(?P<version>\S+)")
_CODE = re.compile(r"^(?P<kind>error|ALARM):(?P<code>\d+)\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class GrblLine:
    """One classified line from a GRBL controller.

    Attributes:
        kind: ``"ok" | "error" | "alarm" | "status" | "msg" | "feedback" | "banner" | "other"``.
        text: the line as received (stripped).
        code: error / alarm number, if any.
        payload: message text (``msg`` / ``feedback``) or firmware version (``banner``).
    """

    kind: str
    text: str
    code: int | None = None
    payload: str = ""


@dataclass(frozen=True)
class GrblStatus:
    """A parsed status report.

    Attributes:
        state: ``Idle``, ``Run``, ``Hold``, ``Jog``, ``Alarm``, ``Door``, ``Check``, ``Home``, ``Sleep``.
        substate: the number after ``:`` (``Hold:0``), or ``None``.
        fields: every ``key:value`` field, values as strings.
        mpos: machine position by axis letter (from ``MPos``, or ``WPos + WCO``), or ``None``.
    """

    state: str
    substate: int | None
    fields: dict[str, str] = field(default_factory=dict)
    mpos: dict[str, float] | None = None


def classify(line: str) -> GrblLine:
    """Classify one received line (pure)."""
    text = line.strip()
    if text == "ok":
        return GrblLine("ok", text)
    m = _CODE.match(text)
    if m:
        return GrblLine("alarm" if m["kind"].upper() == "ALARM" else "error", text, int(m["code"]))
    if text.startswith("<") and text.endswith(">"):
        return GrblLine("status", text)
    if text.startswith("[MSG:") and text.endswith("]"):
        return GrblLine("msg", text, payload=text[5:-1])
    if text.startswith("[") and text.endswith("]"):
        return GrblLine("feedback", text, payload=text[1:-1])
    m = _BANNER.match(text)
    if m:
        return GrblLine("banner", text, payload=m["version"])
    return GrblLine("other", text)


def parse_status(line: str, axes: str = "XYZAB") -> GrblStatus:
    """Parse ``<State|MPos:...|...>`` by key (pure).

    Args:
        line: the report, with its angle brackets.
        axes: the letters of the reported coordinates, in report order (``"XYZ"`` for a
            3-axis GRBL, ``"XYZAB"`` for a 5-axis build).

    ``MPos`` gives machine coordinates directly; with only ``WPos`` the machine position is
    ``WPos + WCO`` when the report carries ``WCO`` (else ``mpos`` is ``None``).
    """
    text = line.strip()
    if not (text.startswith("<") and text.endswith(">")):
        raise ValueError(f"not a GRBL status report: {line!r}")
    head, *rest = text[1:-1].split("|")
    state, _, sub = head.partition(":")
    fields = {}
    for item in rest:
        key, sep, value = item.partition(":")
        if not sep:
            raise ValueError(f"malformed status field {item!r} in {line!r}")
        fields[key] = value

    def coords(key: str) -> dict[str, float] | None:
        if key not in fields:
            return None
        values = [float(v) for v in fields[key].split(",")]
        if len(values) != len(axes):
            raise ValueError(f"{key} has {len(values)} coordinates but the axes are {axes!r}: {line!r}")
        return dict(zip(axes.upper(), values))

    mpos = coords("MPos")
    if mpos is None:
        wpos, wco = coords("WPos"), coords("WCO")
        mpos = None if wpos is None or wco is None else {k: wpos[k] + wco[k] for k in wpos}
    return GrblStatus(state=state, substate=int(sub) if sub else None, fields=fields, mpos=mpos)


def describe(kind: str, code: int) -> str:
    """Readable text for an ``error:N`` / ``ALARM:N``."""
    table = ERRORS if kind == "error" else ALARMS
    return f"{'error' if kind == 'error' else 'ALARM'}:{code} ({table.get(code, 'see the GRBL docs')})"


class GrblController(Controller):
    """GRBL 1.1 driver (see the module docstring for the protocol).

    Args (beyond :class:`~dipnet.rig.controller.Controller`'s):
        status_axes: the letters of the coordinates in status reports, in order.
        wait: ``"dwell"`` (``G4 P0`` then one status check) or ``"poll"`` (``?`` until ``Idle``).
        poll_s: interval between status polls (s).
        reset_on_connect: send a soft reset on connect and wait for the banner.
    """

    dialect = "grbl"

    def __init__(self, url: str, axes=None, *, status_axes: str = "XYZAB", wait: str = "dwell",
                 poll_s: float = 0.02, reset_on_connect: bool = True, **options) -> None:
        super().__init__(url, axes, **options)
        if wait not in ("dwell", "poll"):
            raise ValueError(f"wait must be 'dwell' or 'poll', got {wait!r}")
        self.status_axes = status_axes.upper()
        self.wait = wait
        self.poll_s = float(poll_s)
        self.reset_on_connect = reset_on_connect
        self.version: str | None = None
        self.last_status: GrblStatus | None = None

    def identity(self) -> dict:
        return {**super().identity(), "firmware": self.version, "status_axes": self.status_axes}

    # ------------------------------------------------------------------ lines
    def _handle(self, line: GrblLine, expect_banner: bool = False) -> None:
        """React to pushed lines: raise on alarms and unexpected resets, keep messages."""
        if line.kind == "alarm":
            raise AlarmError(f"controller {describe('alarm', line.code)}", line.code)
        if line.kind == "banner":
            self.version = line.payload
            if not expect_banner:
                raise ResetError(f"controller was reset unexpectedly (banner {line.text!r})")
        elif line.kind in ("msg", "feedback", "other") and line.text:
            self.messages.append(line.text)
        elif line.kind == "status":
            self.last_status = parse_status(line.text, self.status_axes)

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        link = require_link(self)
        link.write_line(line)
        received = []
        while True:
            reply = classify(link.read_line(self.timeout if timeout is None else timeout))
            if reply.kind == "ok":
                return received
            if reply.kind == "error":
                raise ControllerError(f"controller rejected {line!r}: {describe('error', reply.code)}", reply.code)
            self._handle(reply)
            received.append(reply.text)

    def status(self) -> GrblStatus:
        """Send ``?`` and return the parsed report (pushed alarms / resets raise)."""
        link = require_link(self)
        link.write(STATUS_QUERY)
        while True:
            reply = classify(link.read_line(self.timeout))
            if reply.kind == "status":
                self.last_status = parse_status(reply.text, self.status_axes)
                return self.last_status
            if reply.kind == "ok":
                continue  # a late acknowledgement of an earlier line
            if reply.kind == "error":
                raise ControllerError(f"controller {describe('error', reply.code)}", reply.code)
            self._handle(reply)

    def _wait_banner(self, timeout: float) -> None:
        link = require_link(self)
        deadline = time.monotonic() + timeout
        while True:
            reply = classify(link.read_line(max(deadline - time.monotonic(), 1e-3)))
            if reply.kind == "banner":
                self._handle(reply, expect_banner=True)
                return
            if reply.kind in ("msg", "feedback", "other") and reply.text:
                self.messages.append(reply.text)

    # ------------------------------------------------------------------ interface
    def _handshake(self) -> None:
        link = require_link(self)
        if self.reset_on_connect:
            link.discard_input()
            link.write(SOFT_RESET)
            self._wait_banner(self.timeout)
        if self.status().state != "Alarm":
            self.command("G90")

    def _recover(self) -> None:
        for _ in range(3):  # a pending banner or alarm line may come first
            try:
                state = self.status().state
                break
            except (ResetError, AlarmError):
                continue
        else:
            state = "Alarm"
        if state == "Alarm":
            self.command("$X")
            self.command("G90")
        elif state.startswith("Hold") or state == "Door":
            require_link(self).write(b"~")

    def home(self) -> None:
        self.command("$H", timeout=self.home_timeout)

    def unlock(self) -> None:
        """``$X``: leave the alarm state without homing."""
        self.command("$X")

    def wait_idle(self, timeout: float | None = None) -> None:
        limit = self.move_timeout if timeout is None else float(timeout)
        deadline = time.monotonic() + limit
        if self.wait == "dwell":
            self.command("G4 P0", timeout=limit)
        while True:
            st = self.status()
            if st.state == "Idle":
                return
            if st.state == "Alarm":
                raise AlarmError("controller is in the alarm state")
            if time.monotonic() > deadline:
                raise RigTimeout(f"the move did not finish within {limit:g} s (state {st.state})")
            time.sleep(self.poll_s)

    def position(self) -> Position:
        st = self.status()
        if st.mpos is None:
            raise ControllerError(f"status report has no MPos (or WPos + WCO): set $10=1 ({st.fields})")
        return self.axes.rig_position(st.mpos)

    def stop(self) -> None:
        link = require_link(self)
        link.write(FEED_HOLD)
        link.write(SOFT_RESET)
        try:
            self._wait_banner(self.timeout)
        except RigTimeout:
            pass
