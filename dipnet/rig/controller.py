"""The motion-controller interface, its faults, the axis mapping and the line transport.

A dipping rig has one linear axis that lowers the object into the tank and two rotary axes:
``tilt`` tips the object's own z axis away from the vertical and ``spin`` turns the object
about that axis (see :func:`dipnet.core.orientations.rig_to_direction`). Drivers speak one
firmware dialect (:mod:`dipnet.rig.grbl`, :mod:`dipnet.rig.marlin`) over a pyserial port
opened with ``serial.serial_for_url`` (so ``fakerig://`` and ``socket://`` URLs work too).

Positions in the interface are *rig* coordinates: ``lower_mm`` (mm, increasing = lowered
further into the tank), ``tilt_deg`` and ``spin_deg`` (degrees). :class:`AxisMap` turns them
into machine coordinates: ``machine = sign * scale * value + offset`` per axis.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import tempfile
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import serial

from dipnet.core.locks import HeldLock, LockHeld

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- faults
class RigError(RuntimeError):
    """Any fault of the rig (controller, sensor or link). The message is one line."""


class RigTimeout(RigError):
    """No (complete) reply within the time limit."""


class ControllerError(RigError):
    """The controller rejected a command (GRBL ``error:N``, Marlin ``Error:...``)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


class AlarmError(RigError):
    """The controller is in an alarm / halted state (GRBL ``ALARM:N``, Marlin ``kill()``)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


class ResetError(RigError):
    """The controller printed its start-up banner unexpectedly (it was reset)."""


class RigDisconnected(RigError):
    """The serial link is gone (cable pulled, port closed, device vanished)."""


class SensorUnstable(RigError):
    """The sensor did not give a stable reading within the allowed retries."""


class PositionUnknown(RigError):
    """The controller's position cannot be trusted (an alarm or reset that can lose steps):
    nothing may move until the machine is homed or the operator confirms the position."""


class PositionMismatch(RigError):
    """The controller, idle after a move, reports a position other than the one commanded (beyond its step
    resolution): a reading there would be recorded at a position the machine did not reach."""


class MotionHeld(RigError):
    """The controller is in a feed hold or a safety-door state (an operator or a sensor stopped it)."""


class PortBusy(RigError, ValueError):
    """Another process holds the lock of this port (a second scan on the same rig); a user
    error (the CLI prints ``error: ...`` and exits 2)."""


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class Axis:
    """One machine axis.

    Attributes:
        letter: G-code axis letter (``"Z"``, ``"A"``, ...).
        scale: machine units per rig unit (mm per mm, or machine units per degree).
        sign: +1 or -1 (e.g. -1 when the machine's Z grows upwards but ``lower_mm`` grows down).
        offset: machine coordinate of rig value 0.
        wrap: period of a rotary axis that may turn freely (e.g. 360 degrees): moves take the
            short way to an equivalent value; ``None`` for a linear or cable-limited axis.
    """

    letter: str
    scale: float = 1.0
    sign: int = 1
    offset: float = 0.0
    wrap: float | None = None

    def __post_init__(self) -> None:
        if len(self.letter) != 1 or not self.letter.isalpha():
            raise ValueError(f"axis letter must be one letter, got {self.letter!r}")
        if self.sign not in (1, -1):
            raise ValueError(f"axis {self.letter}: sign must be +1 or -1, got {self.sign!r}")
        if not 0 < self.scale < math.inf:  # inf and NaN too: they made 'Zinf'/'Znan' G-code words
            raise ValueError(f"axis {self.letter}: scale must be a finite positive number (machine units per rig "
                             f"unit), got {self.scale!r}")
        if not math.isfinite(self.offset):  # NaN was named only by the scan file's writer, as "Out of range float
            # values are not JSON compliant", naming no option
            raise ValueError(f"axis {self.letter}: offset must be a finite number (the machine coordinate of rig "
                             f"value 0), got {self.offset!r}")
        if self.wrap is not None and not 0 < self.wrap < math.inf:
            raise ValueError(f"axis {self.letter}: wrap must be a positive period or null, got {self.wrap!r}")

    def nearest(self, value: float, current: float | None) -> float:
        """The rig value equivalent to ``value`` (modulo :attr:`wrap`) closest to ``current``:
        the short way round. Unchanged for axes that do not wrap or when ``current`` is unknown."""
        if self.wrap is None or current is None:
            return float(value)
        turns = round((float(current) - float(value)) / self.wrap)
        return float(value) + turns * self.wrap

    def to_machine(self, value: float) -> float:
        return self.sign * self.scale * float(value) + self.offset

    def from_machine(self, value: float) -> float:
        return (float(value) - self.offset) / (self.sign * self.scale)


@dataclass(frozen=True)
class AxisMap:
    """The three rig axes: ``lower`` (mm), ``tilt`` and ``spin`` (degrees)."""

    lower: Axis = field(default_factory=lambda: Axis("Z", sign=-1))
    tilt: Axis = field(default_factory=lambda: Axis("A"))
    spin: Axis = field(default_factory=lambda: Axis("B"))

    def __post_init__(self) -> None:
        letters = [a.letter.upper() for a in (self.lower, self.tilt, self.spin)]
        if len(set(letters)) != 3:
            raise ValueError(f"the three rig axes need distinct letters, got {letters}")

    @classmethod
    def from_config(cls, axes: dict | None) -> "AxisMap":
        """From a plain mapping ``{lower: {letter, scale, sign, offset}, tilt: {...}, spin: {...}}`` (any subset)."""
        axes = dict(axes or {})
        default = cls()
        made = {}
        for name in ("lower", "tilt", "spin"):
            try:
                made[name] = Axis(**{**default.__dict__[name].__dict__, **dict(axes.get(name) or {})})
            except ValueError as exc:  # named by its option: "axis A: ..." named no config key
                raise ValueError(f"rig.controller.axes.{name}: {exc}") from None
        return cls(**made)

    def short_way(self, target: dict[str, float | None], current: dict[str, float]) -> dict[str, float | None]:
        """The rig values a move to ``target`` (``{"lower": mm, "tilt": deg, "spin": deg}``, ``None``
        = axis not moved) commands from ``current`` (the last commanded values): a wrapping axis
        (:attr:`Axis.wrap`) goes to the equivalent value nearest its current one (pure)."""
        return {name: None if value is None else getattr(self, name).nearest(value, current.get(name))
                for name, value in target.items()}

    def route(self, moves: list[dict[str, float | None]], start: dict[str, float]) -> list[dict[str, float | None]]:
        """The rig values each of ``moves`` commands, in order, starting from ``start``: what
        :meth:`Controller.move_to` sends for them, the short way round included (pure)."""
        current, out = dict(start), []
        for target in moves:
            commanded = self.short_way(target, current)
            current.update({k: v for k, v in commanded.items() if v is not None})
            out.append(commanded)
        return out

    def words(self, lower_mm: float | None, tilt_deg: float | None, spin_deg: float | None) -> str:
        """G-code words for the given rig values (``None`` = axis not moved), e.g. ``"Z-10 A5 B0"``."""
        parts = []
        for axis, value in ((self.lower, lower_mm), (self.tilt, tilt_deg), (self.spin, spin_deg)):
            if value is not None:
                parts.append(f"{axis.letter.upper()}{axis.to_machine(value):.4f}")
        return " ".join(parts)

    def rig_position(self, machine: dict[str, float]) -> "Position":
        """Rig position from machine coordinates keyed by axis letter."""
        try:
            return Position(*(a.from_machine(machine[a.letter.upper()]) for a in (self.lower, self.tilt, self.spin)))
        except KeyError as exc:
            raise ControllerError(f"the controller reports no {exc.args[0]} axis (has {sorted(machine)})") from None


@dataclass(frozen=True)
class Position:
    """Rig position: ``lower_mm`` (mm, + = lowered), ``tilt_deg``, ``spin_deg`` (degrees)."""

    lower_mm: float
    tilt_deg: float
    spin_deg: float


# ----------------------------------------------------------------------------- transport
class LineChannel:
    """Line-oriented reads and writes on a pyserial port with deadlines.

    Args:
        port: an open pyserial port (``serial.serial_for_url(url, timeout=...)``).
        terminator: line terminator of incoming lines (``\\r`` before it is stripped too).
        lock: the port's :class:`PortLock`, released on :meth:`close`.

    Attributes:
        on_lost: called with the message of the :class:`RigDisconnected` about to be raised when
            the port fails (a controller records there that its position is unknown).
    """

    def __init__(self, port, terminator: bytes = b"\n", lock: "PortLock | None" = None) -> None:
        self.port = port
        self.terminator = terminator
        self.lock = lock
        self.on_lost: Callable[[str], None] | None = None
        self._buffer = bytearray()

    def _lost(self, exc: BaseException) -> RigDisconnected:
        """The error to raise for a failed port, after telling :attr:`on_lost`."""
        error = RigDisconnected(f"lost the link to {self.port.port}: {exc}")
        if self.on_lost is not None:
            self.on_lost(str(error))
        return error

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from exc

    def write_line(self, text: str) -> None:
        log.debug("> %s", text)
        self.write(text.encode("ascii") + b"\n")

    def read_line(self, timeout: float) -> str:
        """The next line (without terminator and surrounding whitespace); :class:`RigTimeout` if none."""
        deadline = time.monotonic() + timeout
        while True:
            end = self._buffer.find(self.terminator)
            if end >= 0:
                line = bytes(self._buffer[:end]).decode("ascii", errors="replace").strip()
                del self._buffer[:end + len(self.terminator)]
                log.debug("< %s", line)
                return line
            left = deadline - time.monotonic()
            if left <= 0:
                raise RigTimeout(f"no reply from {self.port.port} within {timeout:g} s")
            try:
                waiting = self.port.in_waiting
                chunk = self.port.read(max(1, waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                raise self._lost(exc) from exc
            self._buffer += chunk

    def drain(self, quiet_s: float = 0.1, limit_s: float = 2.0) -> list[str]:
        """Read and return lines until none arrives for ``quiet_s`` (at most ``limit_s``): the
        leftovers of a command interrupted by a fault."""
        lines, deadline = [], time.monotonic() + limit_s
        while time.monotonic() < deadline:
            try:
                lines.append(self.read_line(quiet_s))
            except RigTimeout:
                break
        return lines

    def discard_input(self) -> None:
        """Drop everything received so far."""
        self._buffer.clear()
        try:
            self.port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from exc

    def close(self) -> None:
        try:
            self.port.close()
        except (serial.SerialException, OSError):
            pass
        if self.lock is not None:
            self.lock.release()


class PortLock:
    """An exclusive, non-blocking lock on one port URL, held by this process until
    :meth:`release` (a :class:`dipnet.core.locks.HeldLock` in ``<tmp>/dipnet-port-locks``; the
    operating system drops it when the process dies). ``fakerig://`` URLs live inside one process
    and are not locked.

    Raises:
        PortBusy: another process holds the port.
    """

    directory = Path(tempfile.gettempdir()) / "dipnet-port-locks"

    def __init__(self, url: str) -> None:
        self.url = url
        self.lock: HeldLock | None = None
        if url.startswith("fakerig://"):
            return
        self.path = self.port_file(url, ".lock")
        try:
            self.lock = HeldLock(self.path)
        except LockHeld as exc:
            raise PortBusy(f"port {url} is in use by {exc} (lock {self.path}): "
                           f"another scan is running on this rig; wait for it or stop it") from None

    @classmethod
    def port_file(cls, url: str, suffix: str) -> Path:
        """The file of port ``url`` in :attr:`directory` ending in ``suffix`` (``.lock``: the lock)."""
        name = re.sub(r"[^A-Za-z0-9._-]+", "_", url).strip("_")[:80]
        return cls.directory / f"{name}-{hashlib.sha1(url.encode()).hexdigest()[:8]}{suffix}"

    def release(self) -> None:
        if self.lock is not None:
            self.lock.release()
            self.lock = None


def rig_position_marker(url: str) -> Path | None:
    """Where a run that lost the position of the controller on ``url`` says so for every scan on that rig
    (beside the port's lock, :meth:`PortLock.port_file`), or ``None`` for an in-process ``fakerig://`` world,
    whose position ends with its process."""
    return None if url.startswith("fakerig://") else PortLock.port_file(url, ".position-lost.json")


def open_channel(url: str, terminator: bytes = b"\n", baudrate: int = 115200) -> LineChannel:
    """Lock ``url`` (:class:`PortLock`), open it (:func:`open_port`) and wrap it in a
    :class:`LineChannel` that releases the lock when closed."""
    lock = PortLock(url)
    try:
        return LineChannel(open_port(url, baudrate=baudrate), terminator, lock)
    except BaseException:
        lock.release()
        raise


def open_port(url: str, timeout: float = 0.05, baudrate: int = 115200, **options):
    """``serial.serial_for_url(url, timeout=...)``, with the fake rig's URL scheme registered."""
    from dipnet.rig import register_url_handlers

    register_url_handlers()
    try:
        return serial.serial_for_url(url, timeout=timeout, baudrate=baudrate, **options)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise RigDisconnected(f"cannot open {url}: {exc}") from exc


def seconds(value, name: str, node: str) -> float:
    """``value`` as a time limit in seconds: a positive finite number, else ``ValueError`` naming the option
    ``node.name`` (a limit of 0 or less times out before any reply: the fault would be blamed on the rig)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ValueError(f"{node}.{name} must be a positive number of seconds (a time limit), got {value!r}")
    return float(value)


# ----------------------------------------------------------------------------- interface
class SerialDevice(ABC):
    """A device behind one serial line (:class:`LineChannel` in ``self.link``, ``None`` when closed)."""

    link: LineChannel | None = None

    @abstractmethod
    def connect(self) -> None:
        """Open the port and bring the device to a known state."""

    def reconnect(self) -> None:
        """Close and reopen the port (after a disconnect)."""
        self.close()
        self.connect()

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
            self.link = None


class Controller(SerialDevice):
    """A motion controller of a dipping rig (one firmware dialect).

    Args:
        url: pyserial URL or device (``/dev/ttyUSB0``, ``fakerig://demo/grbl``, ``socket://...``).
        axes: the rig-to-machine axis mapping (or its config dict, see :meth:`AxisMap.from_config`).
        baudrate: serial speed.
        timeout: reply timeout for ordinary commands (s).
        move_timeout: time limit for a move to finish (s).
        home_timeout: time limit for homing (s).
        feed: feed rate of ``G1`` moves (machine units per minute); ``None`` uses ``G0``.

    Safety state: :attr:`position_lost` holds why the position cannot be trusted (an alarm or
    reset that can lose steps, or a link lost after a move was commanded), or ``None``; while it
    is set, :meth:`move_to` refuses to move (:class:`PositionUnknown`) until :meth:`home`
    succeeds or the operator calls :meth:`confirm_position`. :attr:`moved` says whether any
    motion was commanded.
    """

    dialect = "base"

    def __init__(self, url: str, axes: AxisMap | dict | None = None, *, baudrate: int = 115200, timeout: float = 2.0,
                 move_timeout: float = 120.0, home_timeout: float = 120.0, feed: float | None = None) -> None:
        self.url = url
        self.axes = axes if isinstance(axes, AxisMap) else AxisMap.from_config(axes)
        self.baudrate = baudrate
        self.timeout = seconds(timeout, "timeout", "rig.controller")
        self.move_timeout = seconds(move_timeout, "move_timeout", "rig.controller")
        self.home_timeout = seconds(home_timeout, "home_timeout", "rig.controller")
        if feed is not None and (isinstance(feed, bool) or not isinstance(feed, (int, float))
                                 or not 0 < feed < math.inf):
            raise ValueError(f"rig.controller.feed must be a positive feed rate (machine units per minute) or null "
                             f"(G0 rapids), got {feed!r}: G1 moves need a positive F")
        self.feed = feed
        self.messages: list[str] = []  # informational lines pushed by the controller
        self.link: LineChannel | None = None
        self.position_lost: str | None = None
        self.moved = False
        self._target: dict[str, float] = {}  # last commanded rig values (for wrap-around)

    # -- lifecycle
    def connect(self) -> None:
        """Lock and open the port and bring the controller to a known state."""
        self.attach(open_channel(self.url, baudrate=self.baudrate))

    def attach(self, link: LineChannel) -> None:
        """Talk over an open channel (e.g. a recorded-trace replay) and bring the controller to a
        known state."""
        self.link = link
        link.on_lost = self._link_lost
        self._target = {}
        self._handshake()

    def _link_lost(self, reason: str) -> None:
        """The link failed. Once a move was commanded the position is unknown: the machine may
        still be moving, or the board restarted (a power cycle, or the reset an Arduino does when
        its port is opened, sets its position to 0 while the object stays where it was)."""
        if self.moved:
            self.lose_position(f"{reason}, after a move was commanded: the machine may have moved on, or restarted "
                               f"and counts from 0 wherever the object is")

    def identity(self) -> dict:
        """What the rig header records about this controller."""
        return {"dialect": self.dialect, "url": self.url, "axes": {
            name: vars(getattr(self.axes, name)) for name in ("lower", "tilt", "spin")}}

    def check_board(self, home: bool, targets: dict[str, tuple[float, float]],
                    direct: dict[str, tuple[float, float]] | None = None) -> list[str]:
        """Mismatches between this configuration and the board's settings (read at connect), one
        message each; ``targets`` gives the rig range ``(min, max)`` per axis name that the scan's
        moves command (the short way round included, :meth:`AxisMap.route`), ``direct`` the same
        without the short way (``None``: as ``targets``). Dialects that cannot read settings
        return ``[]``."""
        return []

    def can_home(self) -> bool:
        """Whether the board can home (settings read at connect; ``True`` when unknown)."""
        return True

    def lose_position(self, reason: str) -> None:
        """Record that the position can no longer be trusted (see the class docstring)."""
        if self.position_lost is None:
            self.position_lost = reason
        self._target = {}

    def confirm_position(self) -> None:
        """The operator states that the machine position is right (after checking it by hand)."""
        self.position_lost = None

    # -- motion
    def move_to(self, lower_mm: float | None = None, tilt_deg: float | None = None,
                spin_deg: float | None = None) -> None:
        """Queue an absolute move of the given axes (``None`` = leave the axis where it is);
        a wrapping rotary axis (:attr:`Axis.wrap`) goes the short way round.

        Raises:
            PositionUnknown: the position was lost and the machine has not been re-homed.
        """
        if self.position_lost is not None:
            raise PositionUnknown(f"refusing to move: {self.position_lost}")
        target = {"lower": lower_mm, "tilt": tilt_deg, "spin": spin_deg}
        if any(value is not None and getattr(self.axes, name).wrap is not None and name not in self._target
               for name, value in target.items()):
            here = self.position()
            self._target.update(lower=here.lower_mm, tilt=here.tilt_deg, spin=here.spin_deg)
        target = self.axes.short_way(target, self._target)
        words = self.axes.words(target["lower"], target["tilt"], target["spin"])
        if not words:
            return
        motion = "G0" if self.feed is None else "G1"
        feed = "" if self.feed is None else f" F{self.feed:g}"
        self.moved = True
        self.command(f"{motion} {words}{feed}")
        self._target.update({k: v for k, v in target.items() if v is not None})

    def absolute_mm(self) -> None:
        """``G90`` then ``G21``: absolute moves in mm, whatever modes the board kept (a GRBL startup block ``$N0``,
        run after every reset, or an earlier sender: ``G91``, or ``G20``, which makes every move 25.4 x too far).
        A Marlin built without inch support answers ``G21`` with an ``Unknown command`` echo and ``ok``."""
        self.command("G90")
        self.command("G21")

    def check_arrived(self) -> None:
        """After :meth:`wait_idle`: check that the machine stands where the moves since connecting (or homing)
        commanded each axis (the rig values of :meth:`move_to`, the short way round included), in the controller's
        own frame: GRBL's ``MPos``, Marlin's step counts (``M114``'s ``Count``: its logical position only echoes the
        moves). The base class has nothing to compare and returns; so does a dialect whose firmware does not report
        what is needed (it warns once).

        Raises:
            PositionMismatch: the controller reports another position (the message names both and the causes).
        """

    @abstractmethod
    def _handshake(self) -> None:
        """After opening: wait for / provoke the banner, clear buffers, read the settings,
        select absolute moves in mm (:meth:`absolute_mm`) unless the controller is in an alarm state."""

    @abstractmethod
    def settle(self) -> Position:
        """After a fault: stop any motion, resynchronise the line protocol, clear what can be
        cleared without losing the position, and return the position a status report confirms.

        Raises:
            PositionUnknown: the position cannot be trusted (:attr:`position_lost`).
            MotionHeld: a safety door is open.
            RigError: the controller does not answer.
        """

    @abstractmethod
    def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line and wait for its acknowledgement; returns the lines received before it."""

    @abstractmethod
    def home(self) -> None:
        """Home the machine (blocks until done); the position is trusted again afterwards."""

    @abstractmethod
    def wait_idle(self, timeout: float | None = None) -> None:
        """Block until every queued move has finished."""

    @abstractmethod
    def position(self) -> Position:
        """The current rig position (from a status report)."""

    @abstractmethod
    def stop(self) -> None:
        """Halt motion and flush queued moves without losing the position where possible."""


def require_link(controller) -> LineChannel:
    if controller.link is None:
        raise RigDisconnected(f"{controller.url} is not connected: call connect() first")
    return controller.link
