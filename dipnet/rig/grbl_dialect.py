"""GRBL 1.1 dialect: the pure line parsers and settings checks of the :class:`~dipnet.rig.grbl.GrblController` driver.

Protocol facts (GRBL 1.1 interface docs)
----------------------------------------
* Every line sent is answered by ``ok`` or ``error:N``.
* The controller pushes ``ALARM:N``, ``[MSG:...]`` (and other ``[...]`` feedback) at any time;
  after a (soft) reset it prints its banner ``Grbl 1.1h ['$' for help]``.
* Real-time characters are not lines and get no ``ok``: ``?`` asks for a status report
  ``<State|MPos:x,y,z|FS:f,s|WCO:...>`` (fields vary with ``$10``: parse them by key),
  ``!`` feed hold, ``~`` resume, ``0x18`` soft reset.
* States: ``Hold:1`` is a hold still decelerating (a reset then throws ``ALARM:3``),
  ``Hold:0`` a completed hold (a reset keeps the position); ``Door:N`` a safety door.
* After ``ALARM:1`` (hard limit) or ``ALARM:2`` (soft limit) GRBL prints
  ``[MSG:Reset to continue]`` and answers nothing until a soft reset; after a reset it stays
  in ``Alarm`` ("``'$H'|'$X' to unlock``"). Alarms 1, 3 and 6-10 lose the position (re-home).
* ``$H`` homes, ``$X`` unlocks an alarm. ``G4 P0`` is acknowledged only when the planner
  buffer is empty, i.e. when every earlier move has finished.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
FEED_HOLD = b"!"

#: A few GRBL 1.1 error codes, for readable messages.
ERRORS = {1: "expected command letter", 2: "bad number format", 3: "invalid $ statement",
          5: "homing is not enabled ($22=0)", 8: "not idle", 9: "G-code locked out during alarm or jog state",
          10: "soft limits need homing enabled ($22=1)", 15: "travel exceeded (soft limit)",
          20: "unsupported or invalid g-code command", 22: "feed rate not set",
          25: "a g-code word repeated in the block",
          33: "invalid target"}
#: GRBL 1.1 alarm codes.
ALARMS = {1: "hard limit triggered", 2: "soft limit: target exceeds machine travel",
          3: "reset while in motion (position lost)", 4: "probe fail", 5: "probe fail",
          6: "homing fail: reset during homing", 7: "homing fail: door opened", 8: "homing fail: pull-off",
          9: "homing fail: switch not found", 10: "homing fail: second switch not found"}
#: Alarms after which GRBL's alarm table says the machine position is likely lost (re-home).
POSITION_LOST_ALARMS = frozenset({1, 3, 6, 7, 8, 9, 10})
#: Critical alarms: GRBL answers nothing, not even ``?``, until a soft reset.
RESET_ALARMS = frozenset({1, 2})

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


class AxisCountError(ValueError):
    """A status report carries another number of coordinates than the configured axes."""


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
            raise AxisCountError(f"{key} has {len(values)} coordinates but the axes are {axes!r}: {line!r}")
        return dict(zip(axes.upper(), values))

    mpos = coords("MPos")
    if mpos is None:
        wpos, wco = coords("WPos"), coords("WCO")
        mpos = None if wpos is None or wco is None else {k: wpos[k] + wco[k] for k in wpos}
    return GrblStatus(state=state, substate=int(sub) if sub else None, fields=fields, mpos=mpos)


def in_motion(st: GrblStatus) -> bool:
    """Whether a soft reset now would abort a motion and lose the position (``ALARM:3``): running,
    jogging, homing, or a hold still decelerating (``Hold:1``) (pure)."""
    return st.state in ("Run", "Jog", "Home") or (st.state == "Hold" and st.substate == 1)


def describe(kind: str, code: int) -> str:
    """Readable text for an ``error:N`` / ``ALARM:N``."""
    table = ERRORS if kind == "error" else ALARMS
    return f"{'error' if kind == 'error' else 'ALARM'}:{code} ({table.get(code, 'see the GRBL docs')})"


def read_settings(lines: list[str]) -> dict[int, float]:
    """``{number: value}`` from the ``$$`` lines ``$10=1`` (pure)."""
    out = {}
    for text in lines:
        m = re.match(r"^\$(\d+)=([-+]?[\d.]+)", text.strip())
        if m:
            out[int(m[1])] = float(m[2])
    return out


def machine_range(axis, rig: tuple[float, float]) -> tuple[float, float]:
    """Machine ``(min, max)`` of a rig range ``(min, max)`` on ``axis`` (pure)."""
    low, high = sorted((axis.to_machine(rig[0]), axis.to_machine(rig[1])))
    return low, high


def check_settings(settings: dict[int, float], status_axes: str, axes, home: bool,
                   targets: dict[str, tuple[float, float]],
                   direct: dict[str, tuple[float, float]] | None = None) -> list[str]:
    """One message per mismatch between the driver's configuration and a GRBL board (pure).

    Args:
        settings: ``$$`` values.
        status_axes: the configured letters of the reported coordinates.
        axes: the :class:`~dipnet.rig.controller.AxisMap`.
        home: whether the scan homes.
        targets: rig ``(min, max)`` per axis name (``lower``, ``tilt``, ``spin``) that the scan's
            moves command, the short way round of a wrapping axis included.
        direct: the same ranges if every axis turned directly (no wrap); ``None``: as ``targets``.

    The number of reported axes is checked where every status report is parsed
    (:class:`AxisCountError`). With soft limits on, each message says only what makes the moves
    fit: turning directly (``wrap=null``) when that fits, a longer travel ``$13N`` when the moves
    only go too far negative, else another sign/offset (which moves the rig's zero).
    """
    problems = []
    board = "XYZABC"
    for name in ("lower", "tilt", "spin"):
        letter = getattr(axes, name).letter.upper()
        if letter not in status_axes:
            problems.append(f"the {name} axis is on {letter}, which the board does not report "
                            f"(status_axes {status_axes!r}): map it to one of {', '.join(status_axes)}")
    if 10 in settings and not int(settings[10]) & 1:
        problems.append(f"$10={int(settings[10])}: status reports give WPos, not MPos, so positions cannot be "
                        f"read reliably: set $10=1 on the board")
    homing = bool(settings.get(22, 0))
    if home and 22 in settings and not homing:
        problems.append("home=true but homing is disabled on the board ($22=0): enable it ($22=1, with limit "
                        "switches) or scan with home=false")
    if settings.get(20, 0) and homing:
        for name, (low, high) in targets.items():
            axis = getattr(axes, name)
            index = board.find(axis.letter.upper())
            travel = settings.get(130 + index)
            if index < 0 or travel is None:
                continue
            lo, hi = machine_range(axis, (low, high))
            if lo >= -travel - 1e-9 and hi <= 1e-9:
                continue
            fixes = []
            straight = machine_range(axis, (direct or targets).get(name, (low, high)))
            if axis.wrap is not None and straight != (lo, hi) and straight[0] >= -travel - 1e-9 and straight[1] <= 1e-9:
                fixes.append(f"set rig.controller.axes.{name}.wrap=null so that {name} turns directly "
                             f"({axis.letter} {straight[0]:g}..{straight[1]:g} fits)")
            if hi <= 1e-9:
                fixes.append(f"raise ${130 + index} to {-lo:g} if the axis can travel that far")
            if not fixes and hi - lo <= travel + 1e-9:
                fixes.append(f"set rig.controller.axes.{name}.sign/offset so the targets fit in [-{travel:g}, 0]")
            if not fixes:
                fixes.append(f"raise ${130 + index} to {hi - lo:g} if the axis can travel that far and set "
                             f"rig.controller.axes.{name}.sign/offset so the targets fit")
            wrapped = f" (the short way round, wrap={axis.wrap:g})" if axis.wrap is not None else ""
            problems.append(f"soft limits are on ($20=1): GRBL allows {axis.letter} only in [-{travel:g}, 0] "
                            f"after homing, but the scan moves {name} to {axis.letter} {lo:g}..{hi:g}{wrapped}: "
                            + " or ".join(fixes))
    else:  # the machine's size still bounds the lowering
        lower, (low, high) = axes.lower, targets.get("lower", (0.0, 0.0))
        index = board.find(lower.letter.upper())
        travel = settings.get(130 + index) if index >= 0 else None
        span = abs(lower.to_machine(high) - lower.to_machine(low))
        if travel is not None and span > travel + 1e-9:
            problems.append(f"the scan lowers from {low:g} to {high:g} mm ({lower.letter} span {span:g}), more than "
                            f"the board's {lower.letter} travel ${130 + index}={travel:g}: lower protocol.stop_mm, or "
                            f"set ${130 + index} to the machine's travel")
    return problems
