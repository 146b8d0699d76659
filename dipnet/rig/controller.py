"""The motion-controller interface, its faults, the axis mapping and the line transport.

A dipping rig has one linear axis that lowers the object into the tank and two rotary axes:
``tilt`` tips the object's own z axis away from the vertical and ``spin`` turns the object
about that axis (see :func:`dipnet.orientations.rig_to_direction`). Drivers speak one
firmware dialect (:mod:`dipnet.rig.grbl`, :mod:`dipnet.rig.marlin`) over a pyserial port
opened with ``serial.serial_for_url`` (so ``fakerig://`` and ``socket://`` URLs work too).

Positions in the interface are *rig* coordinates: ``lower_mm`` (mm, increasing = lowered
further into the tank), ``tilt_deg`` and ``spin_deg`` (degrees). :class:`AxisMap` turns them
into machine coordinates: ``machine = sign * scale * value + offset`` per axis.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import serial

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


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class Axis:
    """One machine axis.

    Attributes:
        letter: G-code axis letter (``"Z"``, ``"A"``, ...).
        scale: machine units per rig unit (mm per mm, or machine units per degree).
        sign: +1 or -1 (e.g. -1 when the machine's Z grows upwards but ``lower_mm`` grows down).
        offset: machine coordinate of rig value 0.
    """

    letter: str
    scale: float = 1.0
    sign: int = 1
    offset: float = 0.0

    def __post_init__(self) -> None:
        if len(self.letter) != 1 or not self.letter.isalpha():
            raise ValueError(f"axis letter must be one letter, got {self.letter!r}")
        if self.sign not in (1, -1) or not self.scale > 0:
            raise ValueError(f"axis {self.letter}: sign must be +1/-1 and scale positive")

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
    def from_config(cls, cfg: dict | None) -> "AxisMap":
        """From ``{lower: {letter, scale, sign, offset}, tilt: {...}, spin: {...}}`` (any subset)."""
        cfg = dict(cfg or {})
        default = cls()
        return cls(**{name: Axis(**{**default.__dict__[name].__dict__, **dict(cfg.get(name) or {})})
                      for name in ("lower", "tilt", "spin")})

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
    """

    def __init__(self, port, terminator: bytes = b"\n") -> None:
        self.port = port
        self.terminator = terminator
        self._buffer = bytearray()

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise RigDisconnected(f"lost the link to {self.port.port}: {exc}") from exc

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
                raise RigDisconnected(f"lost the link to {self.port.port}: {exc}") from exc
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
            raise RigDisconnected(f"lost the link to {self.port.port}: {exc}") from exc

    def close(self) -> None:
        try:
            self.port.close()
        except (serial.SerialException, OSError):
            pass


def open_port(url: str, timeout: float = 0.05, baudrate: int = 115200, **options):
    """``serial.serial_for_url(url, timeout=...)``, with the fake rig's URL scheme registered."""
    from dipnet.rig import register_url_handlers

    register_url_handlers()
    try:
        return serial.serial_for_url(url, timeout=timeout, baudrate=baudrate, **options)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise RigDisconnected(f"cannot open {url}: {exc}") from exc


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
    """

    dialect = "base"

    def __init__(self, url: str, axes: AxisMap | dict | None = None, *, baudrate: int = 115200, timeout: float = 2.0,
                 move_timeout: float = 120.0, home_timeout: float = 120.0, feed: float | None = None) -> None:
        self.url = url
        self.axes = axes if isinstance(axes, AxisMap) else AxisMap.from_config(axes)
        self.baudrate = baudrate
        self.timeout = float(timeout)
        self.move_timeout = float(move_timeout)
        self.home_timeout = float(home_timeout)
        self.feed = feed
        self.messages: list[str] = []  # informational lines pushed by the controller
        self.link: LineChannel | None = None

    # -- lifecycle
    def connect(self) -> None:
        """Open the port and bring the controller to a known state."""
        self.link = LineChannel(open_port(self.url, baudrate=self.baudrate))
        self._handshake()

    def identity(self) -> dict:
        """What the rig header records about this controller."""
        return {"dialect": self.dialect, "url": self.url, "axes": {
            name: vars(getattr(self.axes, name)) for name in ("lower", "tilt", "spin")}}

    # -- motion
    def move_to(self, lower_mm: float | None = None, tilt_deg: float | None = None,
                spin_deg: float | None = None) -> None:
        """Queue an absolute move of the given axes (``None`` = leave the axis where it is)."""
        words = self.axes.words(lower_mm, tilt_deg, spin_deg)
        if not words:
            return
        motion = "G0" if self.feed is None else "G1"
        feed = "" if self.feed is None else f" F{self.feed:g}"
        self.command(f"{motion} {words}{feed}")

    def safe_lift(self, lower_mm: float) -> None:
        """Recover from a fault if the dialect needs it, then lift to ``lower_mm`` and wait."""
        self.messages += require_link(self).drain()
        self._recover()
        self.move_to(lower_mm=lower_mm)
        self.wait_idle()

    @abstractmethod
    def _handshake(self) -> None:
        """After opening: wait for / provoke the banner, clear buffers, select absolute moves (G90)."""

    @abstractmethod
    def _recover(self) -> None:
        """Make the controller accept motion after an alarm / reset / error."""

    @abstractmethod
    def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line and wait for its acknowledgement; returns the lines received before it."""

    @abstractmethod
    def home(self) -> None:
        """Home the machine (blocks until done)."""

    @abstractmethod
    def wait_idle(self, timeout: float | None = None) -> None:
        """Block until every queued move has finished."""

    @abstractmethod
    def position(self) -> Position:
        """The current rig position."""

    @abstractmethod
    def stop(self) -> None:
        """Halt motion at once and flush queued moves."""


def require_link(controller) -> LineChannel:
    if controller.link is None:
        raise RigDisconnected(f"{controller.url} is not connected: call connect() first")
    return controller.link
