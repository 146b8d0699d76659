"""A fake dipping rig: a simulated tank with an object, speaking the real protocols.

One :class:`FakeRig` is one simulated *world*: a shape (mesh or analytic) held by a stage
with a lowering axis and two rotary axes over a tank of water. Its devices share that world,
so the water level a sensor reports follows the stage position and orientation through the
tank physics of :mod:`dipnet.physics` (``A delta = V(t_start + s + delta)``):

* controllers: ``grbl`` (GRBL 1.1) and ``marlin`` (Marlin 2.x, line numbers and checksums);
* sensors: ``level`` (ASCII line stream, or polled), ``modbus`` (Modbus RTU holding
  registers), ``ad`` (A&D balance) and ``sics`` (MT-SICS balance).

Reach them with pyserial URLs, so the real drivers run unchanged:

* in process: ``fakerig://<name>/<device>`` after ``rig.register("<name>")`` (the URL handler
  is :mod:`dipnet.rig.protocol_fakerig`);
* from another process: :func:`serve` (or ``python -m dipnet.rig.fake MESH``) opens TCP
  servers on 127.0.0.1 and prints ``socket://127.0.0.1:<port>`` URLs.

Geometry: the object's origin sits ``origin_height_mm`` above the resting water when the
stage is at ``lower_mm = 0`` and untilted; the rest is one :class:`~dipnet.rig.geometry.RigGeometry`
(ideal by default; give a mismatched one to make a rig that needs calibration), so the water
line in the object frame is ``t = -origin_height + p (cos r - 1) + e sin r + step_scale lower + delta``
(``r`` the true tilt), the directions follow the true rig angles, the rise uses the true
cross-section and level readings drift by ``level_drift_mm_per_s`` from the world's creation
(the sensor lag is not modelled here).

Faults (:class:`Fault`) fire once, on the n-th motion command the controller receives:
``drop`` (the reply is lost), ``error`` (GRBL ``error:N`` / Marlin ``Error:``), ``alarm``
(GRBL ``ALARM:N`` / Marlin stopped), ``reset`` (banner mid-scan), ``disconnect`` (the link
dies; GRBL: with the move under way, as recorded in ``t4e2`` and ``t4e3``), ``resend``
(Marlin: a corrupted line, answered by ``Resend:``), ``unstable`` (the sensor is noisy and
reports "unstable" for the next ``count`` readings), and for GRBL: ``hold`` (a feed hold
lands half-way through the move), ``door`` (the safety door opens), ``late_ok`` (the next
``G4 P0`` is acknowledged ``delay_s`` late), ``corrupt_status`` / ``split_status`` (the next
status report has one byte corrupted / turned into a newline).

The fake GRBL follows the real firmware's recorded behaviour (``tests/data/grbl-traces``): it
has ``$$`` settings (:data:`GRBL_SETTINGS`, ``grbl_settings`` overrides them), answers ``$I``,
starts in ``Alarm`` when homing is enabled (``$22=1``) and rejects ``$H`` with ``error:5`` when
it is not; ``ALARM:1`` / ``ALARM:2`` (also from soft limits, ``$20=1``: machine space
``[-$13N, 0]``) are followed by ``[MSG:Reset to continue]`` and silence, even to ``?``, until a
soft reset; a reset while moving (or in ``Hold:1``) gives ``ALARM:3``; a held ``G4 P0`` is
acknowledged only after ``~`` or a reset.

Sensor noise is drawn from a generator keyed by the seed, the stage position and the count of
readings since the last move command, so a resumed scan reads the same noise as an
uninterrupted one.
"""

from __future__ import annotations

import argparse
import re
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from dipnet.physics import Tank
from dipnet.rig import marlin, sensors
from dipnet.rig.controller import AxisMap, Position
from dipnet.rig.geometry import RigGeometry, as_geometry

DEVICES = ("grbl", "marlin", "level", "modbus", "ad", "sics")
FAULTS = ("drop", "error", "alarm", "reset", "disconnect", "resend", "unstable", "hold", "door", "late_ok",
          "corrupt_status", "split_status")
#: Stock GRBL 1.1 settings (as read from the firmware, ``tests/data/grbl-traces/t1.log``) with
#: homing enabled; per-axis ``$10N``..``$13N`` are repeated for every status axis.
GRBL_SETTINGS = {0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0,
                 22: 1, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0}
_GRBL_AXIS_SETTINGS = {100: 250.0, 110: 500.0, 120: 10.0, 130: 200.0}
WORLDS: dict[str, "FakeRig"] = {}

_GRBL_BANNER = "Grbl 1.1h ['$' for help]"
_TABLE_STEP_MM = 0.05


@dataclass
class Fault:
    """A fault injected once, when the controller receives its ``at_move``-th motion command.

    Attributes:
        kind: one of :data:`FAULTS`.
        at_move: 1-based count of motion commands (``G0``/``G1``) over the world's lifetime.
        code: the GRBL error / alarm number.
        count: for ``unstable``: how many sensor readings are affected.
        delay_s: for ``late_ok``: how late the acknowledgement comes (s).
    """

    kind: str
    at_move: int
    code: int = 1
    count: int = 50
    delay_s: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in FAULTS:
            raise ValueError(f"unknown fault {self.kind!r}; choose one of {FAULTS}")
        if int(self.at_move) < 1:
            raise ValueError(f"fault at_move must be >= 1, got {self.at_move}")


@dataclass
class SensorFormat:
    """How the fake sensors talk (match the driver's configuration).

    Attributes:
        level_format: Python format of a level line (``{value}`` in mm).
        level_terminator: terminator of level lines.
        level_query: query the level sensor answers; ``None``: it streams.
        modbus_slave, modbus_address, modbus_data_type, modbus_word_order, modbus_scale: the
            register holding the level, ``raw = level / scale``.
        balance_decimals: decimals of the balance readings (g).
    """

    level_format: str = "L={value:.3f} mm"
    level_terminator: str = "\r\n"
    level_query: str | None = None
    modbus_slave: int = 1
    modbus_address: int = 0
    modbus_data_type: str = "int32"
    modbus_word_order: str = "big"
    modbus_scale: float = 0.001
    balance_decimals: int = 3


class FakeRig:
    """The simulated world (see the module docstring).

    Args:
        shape: a :class:`~dipnet.shapes.Shape`, or a mesh path (loaded with ``radius``).
        radius: mesh scale (mm) when ``shape`` is a path.
        tank: the tank (default :meth:`Tank.default`).
        origin_height_mm: height of the object's origin over the resting water at
            ``lower_mm = 0``, untilted (default: the shape's radius + 10 mm).
        pivot_mm: distance of the tilt pivot above the object's origin, along its axis (a
            shorthand for ``geometry.pivot_mm``; non-zero overrides it).
        geometry: the rig's true geometry (:class:`~dipnet.rig.geometry.RigGeometry` or a mapping).
        axes, status_axes: the machine axis mapping and GRBL status order (as the driver's).
        level_sigma_mm, level_quantum_mm: level noise and resolution (mm).
        balance_sigma_g, balance_quantum_g: balance noise and resolution (g).
        density_g_per_mm3: water density.
        unstable_sigma: noise (sensor units: mm or g) during an ``unstable`` fault.
        latency_s: delay of every reply (s).
        move_s: duration of every move (s); 0 = instant.
        keepalive_s: Marlin ``echo:busy`` interval (s).
        faults: faults to inject.
        sensor_format: :class:`SensorFormat`.
        seed: noise seed.
        grbl_settings: ``$$`` values overriding :data:`GRBL_SETTINGS` (e.g. ``{22: 0}``: no homing).
    """

    def __init__(self, shape, *, radius: float | None = None, tank: Tank | None = None,
                 origin_height_mm: float | None = None, pivot_mm: float = 0.0,
                 geometry: RigGeometry | dict | None = None, axes: AxisMap | dict | None = None,
                 status_axes: str = "XYZAB", level_sigma_mm: float = 0.0, level_quantum_mm: float = 0.001,
                 balance_sigma_g: float = 0.0, balance_quantum_g: float = 0.001, density_g_per_mm3: float = 1e-3,
                 unstable_sigma: float = 0.5, latency_s: float = 0.0, move_s: float = 0.0, keepalive_s: float = 2.0,
                 faults: list[Fault | dict] | None = None, sensor_format: SensorFormat | dict | None = None,
                 seed: int = 0, name: str = "fakerig", grbl_settings: dict | None = None) -> None:
        if isinstance(shape, str):
            from dipnet.shapes import load_mesh

            shape = load_mesh(shape, radius=radius)
        self.shape = shape
        self.name = name
        self.tank = tank or Tank.default(3)
        r = float(shape.radius())
        self.origin_height_mm = r + 10.0 if origin_height_mm is None else float(origin_height_mm)
        geometry = as_geometry(geometry)
        self.geometry = geometry.with_values(pivot_mm=float(pivot_mm)) if pivot_mm else geometry
        self.created = time.monotonic()
        self.axes = axes if isinstance(axes, AxisMap) else AxisMap.from_config(axes)
        self.status_axes = status_axes.upper()
        self.level_sigma_mm, self.level_quantum_mm = float(level_sigma_mm), float(level_quantum_mm)
        self.balance_sigma_g, self.balance_quantum_g = float(balance_sigma_g), float(balance_quantum_g)
        self.density = float(density_g_per_mm3)
        self.unstable_sigma = float(unstable_sigma)
        self.latency_s, self.move_s, self.keepalive_s = float(latency_s), float(move_s), float(keepalive_s)
        self.faults = faults
        self.sensor_format = sensor_format if isinstance(sensor_format, SensorFormat) \
            else SensorFormat(**dict(sensor_format or {}))
        self.seed = seed
        self.grbl_settings = {**GRBL_SETTINGS, **{
            base + i: value for i in range(len(self.status_axes)) for base, value in _GRBL_AXIS_SETTINGS.items()},
            **{int(k): v for k, v in dict(grbl_settings or {}).items()}}
        self.lock = threading.RLock()
        self._tables: dict[tuple[float, float], tuple[np.ndarray, np.ndarray, float]] = {}
        self.reset(self.faults)

    def reset(self, faults: list[Fault | dict] | None = None) -> "FakeRig":
        """Back to the power-up state (stage at 0, counters zero, noise re-seeded; in ``Alarm`` if
        homing is enabled, as GRBL) with new ``faults``; the cached physics tables are kept.
        Returns itself."""
        with self.lock:
            self.faults = [f if isinstance(f, Fault) else Fault(**f) for f in (faults or [])]
            self.fired = []
            self.reads_since_move = 0
            self.motion_count = 0
            self.reads = 0  # sensor readings served
            self.unstable_left = 0
            self.alarm = bool(self.grbl_settings.get(22))
            self.critical = False  # GRBL after ALARM:1/2: silent until a soft reset
            self.max_lower_seen = 0.0  # deepest lowering reached (mm)
            self._move = (Position(0.0, 0.0, 0.0), Position(0.0, 0.0, 0.0), 0.0, 0.0)  # start, end, t0, t1
        return self

    # ------------------------------------------------------------------ registry
    def register(self, name: str | None = None) -> "FakeRig":
        """Make the world reachable as ``fakerig://<name>/<device>``; returns itself."""
        self.name = name or self.name
        WORLDS[self.name] = self
        return self

    def url(self, device: str) -> str:
        """The in-process URL of ``device`` (the world must be registered)."""
        if device not in DEVICES:
            raise ValueError(f"unknown fake device {device!r}; choose one of {DEVICES}")
        return f"fakerig://{self.name}/{device}"

    # ------------------------------------------------------------------ motion
    def position(self, now: float | None = None) -> Position:
        """Where the stage is now (linear motion between the last move's end points)."""
        start, end, t0, t1 = self._move
        now = time.monotonic() if now is None else now
        if now >= t1 or t1 <= t0:
            return end
        f = (now - t0) / (t1 - t0)
        return Position(*(a + f * (b - a) for a, b in zip(vars(start).values(), vars(end).values())))

    def moving(self) -> bool:
        return time.monotonic() < self._move[3]

    def move_end(self) -> float:
        return self._move[3]

    def start_move(self, target: dict[str, float | None]) -> None:
        """Move towards rig values ``{"lower_mm": .., "tilt_deg": .., "spin_deg": ..}`` (None = stay)."""
        with self.lock:
            now = time.monotonic()
            here = self.position(now)
            end = Position(*(here.__dict__[k] if target.get(k) is None else float(target[k])
                             for k in ("lower_mm", "tilt_deg", "spin_deg")))
            self._move = (here, end, now, now + self.move_s)
            self.reads_since_move = 0
            self.max_lower_seen = max(self.max_lower_seen, end.lower_mm)

    def halt(self) -> None:
        """Stop where the stage is now."""
        with self.lock:
            here = self.position()
            self._move = (here, here, 0.0, 0.0)

    def machine_position(self) -> dict[str, float]:
        pos = self.position()
        out = {a: 0.0 for a in self.status_axes}
        for axis, value in ((self.axes.lower, pos.lower_mm), (self.axes.tilt, pos.tilt_deg),
                            (self.axes.spin, pos.spin_deg)):
            out[axis.letter.upper()] = axis.to_machine(value)
        return out

    def target_from_words(self, words: dict[str, float]) -> dict[str, float | None]:
        """Rig target from G-code words by axis letter."""
        out = {}
        for key, axis in (("lower_mm", self.axes.lower), ("tilt_deg", self.axes.tilt), ("spin_deg", self.axes.spin)):
            letter = axis.letter.upper()
            out[key] = axis.from_machine(words[letter]) if letter in words else None
        return out

    def on_motion(self) -> Fault | None:
        """Count a motion command; returns the fault that fires on it, if any."""
        with self.lock:
            self.motion_count += 1
            for fault in self.faults:
                if fault.at_move == self.motion_count:
                    self.faults.remove(fault)
                    self.fired.append(fault)
                    if fault.kind == "unstable":
                        self.unstable_left = fault.count
                        return None
                    return fault
        return None

    # ------------------------------------------------------------------ physics
    def waterline_start(self, tilt_deg: float) -> float:
        """Water line height (object frame) at ``lower_mm = 0`` for a tilt, before any rise (mm)."""
        return float(self.geometry.start_heights(tilt_deg, -self.origin_height_mm))

    def deepest_lower_mm(self, max_tilt_deg: float = 90.0) -> float:
        """The deepest lowering (mm) that keeps the object's bounding sphere off the tank bottom
        at every tilt up to ``max_tilt_deg``: the resting water is ``tank.rest_level_mm`` deep and
        at lowering ``s`` the object's origin is ``t_start(tilt) + step_scale s`` below it."""
        tilts = np.linspace(0.0, max(float(max_tilt_deg), 0.0), 91)
        start = max(self.waterline_start(float(t)) for t in tilts)
        return (self.tank.rest_level_mm - float(self.shape.radius()) - start) / self.geometry.step_scale

    def _table(self, tilt: float, spin: float) -> tuple[np.ndarray, np.ndarray, float]:
        """``(stage (n,), rise (n,), full rise)`` for one orientation, cached.

        The fixed point ``A delta = V(t_start + s + delta)`` of :mod:`dipnet.physics` is solved
        on a table of ``V`` with ``_TABLE_STEP_MM`` spacing (one exact ``volume_below`` call per
        orientation, so the fake stays fast); the tests check it against
        :func:`dipnet.physics.solve_dip`.
        """
        key = (round(tilt, 6), round(spin, 6))
        if key not in self._tables:
            direction = self.geometry.directions(tilt, spin)
            r = float(self.shape.radius())
            heights = np.arange(-r - 1.0, r + 1.0 + _TABLE_STEP_MM, _TABLE_STEP_MM)
            volume = self.shape.volume_below(direction, torch.from_numpy(heights))[0].numpy()
            volume = np.maximum.accumulate(np.maximum(volume, 0.0))
            area = self.geometry.area(self.tank.cross_section_mm2)
            # water line t = t0 + c s + V(t) / A  <=>  s = (t - t0 - V(t) / A) / c, increasing in t (a(t) < A)
            stage = (heights - self.waterline_start(tilt) - volume / area) / self.geometry.step_scale
            if np.any(np.diff(stage) <= 0):
                raise ValueError(f"the object's cross-section is not smaller than the tank's ({area:g} mm^2)")
            self._tables[key] = (stage, volume / area, float(volume[-1]) / area)
        return self._tables[key]

    def rise_mm(self) -> float:
        """The water rise (mm) for the stage's current position and orientation."""
        pos = self.position()
        stage, rise, full = self._table(pos.tilt_deg, pos.spin_deg)
        return float(np.interp(pos.lower_mm, stage, rise, left=0.0, right=full))

    def noise(self) -> np.random.Generator:
        """The generator of the next reading's noise: keyed by the seed, the stage position and
        the number of readings since the last move command (see the module docstring)."""
        self.reads_since_move += 1
        pos = self.position()
        key = [int(round(v * 1000)) % 2 ** 40 for v in (pos.lower_mm, pos.tilt_deg, pos.spin_deg)]
        return np.random.default_rng([int(self.seed), self.reads_since_move, *key])

    def read(self, quantity: str) -> tuple[float, bool]:
        """A noisy, quantised reading: ``("level_mm" -> mm | "mass_g" -> g, stable)``."""
        with self.lock:
            self.reads += 1
            rng = self.noise()
            rise = self.rise_mm()
            unstable = self.unstable_left > 0
            self.unstable_left = max(0, self.unstable_left - 1)
            if quantity == "level_mm":
                drift = self.geometry.level_drift_mm_per_s * (time.monotonic() - self.created)
                value, sigma, q = self.tank.rest_level_mm + rise + drift, self.level_sigma_mm, self.level_quantum_mm
            else:
                value, sigma, q = self.density * self.geometry.area(self.tank.cross_section_mm2) * rise, \
                    self.balance_sigma_g, \
                    self.balance_quantum_g
            if unstable:
                sigma = max(sigma, self.unstable_sigma)
            if sigma > 0:
                value += float(rng.normal(0.0, sigma))
            if q > 0:
                value = round(value / q) * q
            return value, not unstable


# ============================================================================ devices
class Device:
    """One end of a link to the world: bytes in (:meth:`receive`), timed bytes out (:meth:`read`)."""

    streaming = False

    def __init__(self, world: FakeRig) -> None:
        self.world = world
        self.out: deque[tuple[float, bytes]] = deque()
        self.cond = threading.Condition()
        self.dead = False
        self._inbuf = bytearray()
        self.on_open()

    def on_open(self) -> None:
        """Called once when the link opens (banners)."""

    def emit(self, text: str | bytes, at: float | None = None, terminator: bytes = b"\r\n",
             realtime: bool = False) -> None:
        """Queue output ready at ``at`` (default now) plus the latency. Ordinary output keeps its
        order (a reply scheduled late holds back the replies after it, as a firmware answering
        lines in order does); ``realtime`` output (status reports) overtakes it."""
        data = text if isinstance(text, bytes) else text.encode("ascii") + terminator
        ready = (time.monotonic() if at is None else at) + self.world.latency_s
        with self.cond:
            if realtime:
                i = len(self.out)
                while i and self.out[i - 1][0] > ready:
                    i -= 1
                self.out.insert(i, (ready, data))
            else:
                ready = max([ready] + [t for t, _ in self.out])
                self.out.append((ready, data))
            self.cond.notify_all()

    def receive(self, data: bytes) -> None:
        self._inbuf += data
        self.parse_input()

    def parse_input(self) -> None:
        """Consume ``self._inbuf``."""

    def poll(self) -> None:
        """Periodic work (streaming, keep-alives); called before every read."""

    def take(self, size: int, timeout: float | None) -> bytes:
        """Up to ``size`` ready bytes, waiting at most ``timeout`` s for the first ones."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.cond:
            while True:
                self.poll()
                now = time.monotonic()
                if self.out and self.out[0][0] <= now:
                    ready, data = self.out.popleft()
                    if len(data) > size:
                        self.out.appendleft((ready, data[size:]))
                        data = data[:size]
                    return data
                if self.streaming and not self.out:
                    self.stream_line()
                    continue
                wait = 0.005 if not self.out else min(0.005, self.out[0][0] - now)
                if deadline is not None:
                    if now >= deadline:
                        return b""
                    wait = min(wait, deadline - now)
                self.cond.wait(max(wait, 1e-4))

    def pending(self) -> int:
        now = time.monotonic()
        with self.cond:
            return sum(len(d) for t, d in self.out if t <= now)

    def clear_output(self) -> None:
        with self.cond:
            self.out.clear()

    def stream_line(self) -> None:
        """Produce one line of a streaming sensor."""

    def lines(self, terminator: bytes = b"\n"):
        while True:
            end = self._inbuf.find(terminator)
            if end < 0:
                return
            line = bytes(self._inbuf[:end]).decode("ascii", errors="replace").strip()
            del self._inbuf[:end + len(terminator)]
            yield line


def _words(line: str) -> dict[str, float]:
    return {m[1].upper(): float(m[2]) for m in re.finditer(r"([A-Za-z])\s*([-+]?\d*\.?\d+)", line)}


class GrblDevice(Device):
    """A GRBL 1.1 controller (resets when the port opens, like an Arduino on DTR); see the
    module docstring for what it reproduces from the recorded firmware."""

    def on_open(self) -> None:
        self.hold = None  # None, or the substate to report next (1 while decelerating, then 0)
        self.held_target: dict | None = None  # the rest of the held move
        self.held_dwell = False  # a G4 P0 waiting for the hold to end
        self.door = False
        self.late_s = 0.0
        self.status_fault: str | None = None
        self.world.critical = False
        self.banner()

    def banner(self) -> None:
        self.emit("")
        self.emit(_GRBL_BANNER)
        if self.world.alarm:
            self.emit("[MSG:'$H'|'$X' to unlock]")

    def parse_input(self) -> None:
        w = self.world
        while self._inbuf:
            for i, byte in enumerate(self._inbuf):  # real-time commands act at once, even mid-line
                if byte in b"?!~\x18":
                    del self._inbuf[i]
                    with w.lock:
                        self.realtime(byte)
                    break
            else:
                break
        for line in self.lines():
            if line and not w.critical:
                with w.lock:
                    self.line(line)

    def state(self) -> str:
        w = self.world
        if w.alarm:
            return "Alarm"
        if self.door:
            return "Door:1"
        if self.hold is not None:
            state = f"Hold:{self.hold}"
            self.hold = 0  # the hold completes after one report of Hold:1
            return state
        return "Run" if w.moving() else "Idle"

    def report(self) -> None:
        w = self.world
        mpos = w.machine_position()
        kind = "MPos" if int(w.grbl_settings.get(10, 1)) & 1 else "WPos"  # work offsets are 0 here
        text = f"<{self.state()}|{kind}:{','.join(f'{mpos[a]:.3f}' for a in w.status_axes)}|FS:0,0>"
        if self.status_fault == "corrupt_status":  # as in t3f.log: '|' read as ':'
            text = text.replace("|FS", ":FS")
        elif self.status_fault == "split_status":  # as in t3g.log: one byte became a newline
            cut = text.rindex("|") + 2
            text = text[:cut] + "\n" + text[cut + 1:]
        self.status_fault = None
        self.emit(text, realtime=True)

    def realtime(self, byte: int) -> None:
        w = self.world
        if byte == 0x18:
            self.soft_reset()
        elif w.critical:
            return  # only a reset is heard
        elif byte == ord("?"):
            self.report()
        elif byte == ord("!") and w.moving() and self.hold is None:
            self.start_hold(dict(zip(("lower_mm", "tilt_deg", "spin_deg"), vars(w._move[1]).values())))
        elif byte == ord("~") and self.hold is not None and not self.door:
            self.hold = None
            if self.held_target is not None:
                w.start_move(self.held_target)
                self.held_target = None
            if self.held_dwell:
                self.held_dwell = False
                self.emit("ok", at=w.move_end())

    def start_hold(self, target: dict) -> None:
        self.world.halt()
        self.hold, self.held_target = 1, target

    def soft_reset(self) -> None:
        """0x18: stop at once; a reset while moving or decelerating loses the position (ALARM:3);
        a held dwell is answered first, as the recorded firmware does."""
        w = self.world
        self.clear_output()
        if w.moving() or self.hold == 1:
            w.alarm = True
            self.emit("ALARM:3")
        w.halt()
        if self.held_dwell:
            self.emit("ok")
        self.hold, self.held_target, self.held_dwell = None, None, False
        w.critical = False
        self.banner()

    def alarm(self, code: int) -> None:
        w = self.world
        w.halt()
        w.alarm = True
        self.emit(f"ALARM:{code}")
        if code in (1, 2):
            self.emit("[MSG:Reset to continue]")
            w.critical = True

    def system(self, upper: str) -> None:
        """``$`` commands."""
        w = self.world
        settings = w.grbl_settings
        if upper == "$X":
            w.alarm = False
            self.emit("[MSG:Caution: Unlocked]")
            self.emit("ok")
        elif upper == "$H":
            if not settings.get(22):
                self.emit("error:5")
                return
            w.start_move({"lower_mm": 0.0, "tilt_deg": 0.0, "spin_deg": 0.0})
            w.alarm = False
            self.emit("ok", at=w.move_end())
        elif upper == "$$":
            for key in sorted(settings):
                value = settings[key]
                self.emit(f"${key}={value:.3f}" if isinstance(value, float) else f"${key}={value}")
            self.emit("ok")
        elif upper == "$I":
            self.emit("[VER:1.1h.20190830:]")
            self.emit("[OPT:V,15,128]")
            self.emit("ok")
        elif re.match(r"^\$\d+=", upper):
            key, value = upper[1:].split("=", 1)
            settings[int(key)] = float(value) if "." in value else int(value)
            self.emit("ok")
        else:
            self.emit("ok")

    def outside_soft_limits(self, words: dict[str, float]) -> bool:
        settings = self.world.grbl_settings
        if not (settings.get(20) and settings.get(22)):
            return False
        return any(not (-settings.get(130 + "XYZABC".index(a), 0.0) <= v <= 0.0) for a, v in words.items()
                   if a in "XYZABC")

    def line(self, line: str) -> None:
        w = self.world
        upper = line.upper()
        if upper.startswith("$"):
            self.system(upper)
        elif w.alarm:
            self.emit("error:9")
        elif re.search(r"\bG0*4\b", upper):
            if self.hold is not None or self.door:
                self.held_dwell = True
            else:
                self.emit("ok", at=w.move_end() + self.late_s)
            self.late_s = 0.0
        elif re.search(r"\bG0*[01]\b", upper):
            self.motion(upper)
        elif re.match(r"^(G9[01]|G2[01]|G5[4-9]|M[0-9]+)\b", upper):
            self.emit("ok")
        else:
            self.emit("error:20")

    def motion(self, upper: str) -> None:
        w = self.world
        fault = w.on_motion()
        kind = None if fault is None else fault.kind
        if kind == "error":
            self.emit(f"error:{fault.code}")
            return
        if kind == "reset":  # a power glitch: the board restarts
            w.halt()
            w.alarm = bool(w.grbl_settings.get(22))
            self.on_open()
            return
        words = _words(re.sub(r"\bG\d+\b|\bF[-+\d.]+", "", upper))
        if self.outside_soft_limits(words):
            self.alarm(2)
            return
        target = w.target_from_words(words)
        if kind == "disconnect":  # the link dies with the move under way (t4e2, t4e3)
            w.start_move(target)
            self.dead = True
            return
        if kind == "alarm":
            w.start_move(target)
            self.alarm(fault.code)
            return
        if kind == "hold":  # lands half-way
            here = w.position()
            half = {k: None if v is None else (getattr(here, k) + v) / 2 for k, v in target.items()}
            w.start_move(half)
            self.emit("ok")
            self.start_hold(target)
            return
        w.start_move(target)
        if kind == "door":
            w.halt()
            self.door = True
        elif kind == "late_ok":
            self.late_s = fault.delay_s
        elif kind in ("corrupt_status", "split_status"):
            self.status_fault = kind
        if kind != "drop":
            self.emit("ok")


class MarlinDevice(Device):
    """A Marlin 2.x controller (line numbers + checksums checked when present)."""

    def on_open(self) -> None:
        self.last_n = 0
        self.stopped = False
        self.corrupt_next = False
        self.emit("start")
        self.emit("echo:Marlin 2.1.2.1")
        self.emit("echo: Last Updated: 2023-05-25 | Author: (dipnet fake rig)")

    def parse_input(self) -> None:
        for line in self.lines():
            if line:
                with self.world.lock:
                    self.line(line)

    def resend(self, reason: str) -> None:
        self.emit(f"Error:{reason}, Last Line: {self.last_n}")
        self.emit(f"Resend: {self.last_n + 1}")
        self.emit("ok")

    def line(self, raw: str) -> None:
        w = self.world
        text = raw
        m = re.match(r"^N(-?\d+)\s+(.*?)\*(\d+)$", raw)
        if m:
            n, body, cs = int(m[1]), m[2], int(m[3])
            if cs != marlin.checksum(raw[:raw.rindex("*")]) or self.corrupt_next:
                self.corrupt_next = False
                self.resend("checksum mismatch")
                return
            if body.upper().startswith("M110"):
                self.last_n = int(_words(body).get("N", n))
                self.emit("ok")
                return
            if n != self.last_n + 1:
                self.resend("Line Number is not Last Line Number+1")
                return
            self.last_n = n
            text = body
        upper = text.upper().strip()
        code = upper.split()[0] if upper else ""
        if code == "M110":
            self.last_n = int(_words(upper[4:]).get("N", 0))
            self.emit("ok")
        elif code == "M999":
            self.stopped = False
            self.emit("ok")
        elif self.stopped:
            self.emit("Error:Printer stopped due to errors. Fix the error and use M999 to restart.")
            self.emit("ok")
        elif code in ("G0", "G1", "G00", "G01"):
            fault = w.on_motion()
            kind = None if fault is None else fault.kind
            if kind == "error":
                self.emit("Error:Move out of range")
                self.emit("ok")
                return
            if kind == "disconnect":
                self.dead = True
                return
            if kind == "reset":
                w.halt()
                self.on_open()
                return
            if kind == "resend":
                self.last_n -= 1
                self.resend("checksum mismatch")
                return
            w.start_move(w.target_from_words(_words(re.sub(r"^G0*[01]|\bF[-+\d.]+", "", upper))))
            if kind == "alarm":
                w.halt()
                self.stopped = True
                self.emit("Error:Printer stopped due to errors. Fix the error and use M999 to restart.")
                self.emit("ok")
                return
            if kind != "drop":
                self.emit("ok")
        elif code == "G28":
            w.start_move({"lower_mm": 0.0, "tilt_deg": 0.0, "spin_deg": 0.0})
            self.wait_ok()
        elif code == "M400":
            self.wait_ok()
        elif code == "M114":
            pos = w.machine_position()
            axes = " ".join(f"{a}:{pos[a]:.2f}" for a in pos)
            self.emit(f"{axes} E:0.00 Count {' '.join(f'{a}:{round(pos[a] * 400)}' for a in pos)}")
            self.emit("ok")
        elif code == "M410":
            w.halt()
            self.emit("ok")
        elif code in ("G90", "G91", "G92", "G21", "M17", "M18", "M84", "M115"):
            self.emit("ok")
        else:
            self.emit(f'echo:Unknown command: "{text}"')
            self.emit("ok")

    def wait_ok(self) -> None:
        """``ok`` when the move ends, with ``echo:busy: processing`` every keep-alive interval."""
        now, end = time.monotonic(), self.world.move_end()
        t = now + self.world.keepalive_s
        while t < end:
            self.emit("echo:busy: processing", at=t)
            t += self.world.keepalive_s
        self.emit("ok", at=max(end, now))


class LevelDevice(Device):
    """An ASCII level sensor: streams lines, or answers a query (``SensorFormat.level_query``)."""

    def on_open(self) -> None:
        fmt = self.world.sensor_format
        self.streaming = fmt.level_query is None
        self.term = fmt.level_terminator.encode("ascii").decode("unicode_escape").encode("ascii")

    def stream_line(self) -> None:
        value, stable = self.world.read("level_mm")
        self.emit(self.world.sensor_format.level_format.format(value=value), terminator=self.term)

    def parse_input(self) -> None:
        query = self.world.sensor_format.level_query
        if query is None:
            self._inbuf.clear()
            return
        q = query.encode("ascii").decode("unicode_escape").encode("ascii")
        while q in self._inbuf:
            del self._inbuf[:self._inbuf.index(q) + len(q)]
            self.stream_line()


def crc16(data: bytes) -> int:
    """Modbus CRC-16 (polynomial 0xA001 reflected, initial 0xFFFF) of ``data`` (pure)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(body: bytes) -> bytes:
    """``body`` followed by its CRC, low byte first (a Modbus RTU frame)."""
    return body + struct.pack("<H", crc16(body))


class ModbusDevice(Device):
    """A Modbus RTU slave holding the level in its registers (function 0x03 only)."""

    def parse_input(self) -> None:
        fmt = self.world.sensor_format
        while len(self._inbuf) >= 8:
            frame, self._inbuf = bytes(self._inbuf[:8]), self._inbuf[8:]
            if crc16(frame) != 0 or frame[0] != fmt.modbus_slave:
                continue  # a real slave stays silent on bad frames
            _, function, address, count = struct.unpack(">BBHH", frame[:6])
            if function != 0x03:
                self.emit(with_crc(bytes([frame[0], function | 0x80, 1])))
                continue
            words = sensors.DATA_TYPES[fmt.modbus_data_type][0]
            if address != fmt.modbus_address or count != words:
                self.emit(with_crc(bytes([frame[0], 0x83, 2])))
                continue
            value, _ = self.world.read("level_mm")
            regs = sensors.encode_registers(value / fmt.modbus_scale, fmt.modbus_data_type, fmt.modbus_word_order)
            self.emit(with_crc(struct.pack(f">BBB{count}H", frame[0], 3, 2 * count, *regs)))


class BalanceDevice(Device):
    """A balance under the tank, A&D (``Q``) or MT-SICS (``S``/``SI``) style."""

    style = "ad"

    def parse_input(self) -> None:
        dec = self.world.sensor_format.balance_decimals
        for line in self.lines():
            cmd = line.strip().upper()
            if not cmd:
                continue
            value, stable = self.world.read("mass_g")
            if self.style == "ad":
                if cmd not in ("Q", "S"):
                    self.emit("EC,E01")
                    continue
                self.emit(f"{'ST' if stable else 'US'},{value:+0{9}.{dec}f}  g")
            elif cmd in ("S", "SI"):
                self.emit(f"S {'S' if stable else 'D'} {value:>10.{dec}f} g")
            else:
                self.emit("ES")


class SicsDevice(BalanceDevice):
    style = "sics"


_DEVICE_CLASSES = {"grbl": GrblDevice, "marlin": MarlinDevice, "level": LevelDevice, "modbus": ModbusDevice,
                   "ad": BalanceDevice, "sics": SicsDevice}


def make_device(world: FakeRig, kind: str) -> Device:
    """A new link to ``world``'s device ``kind`` (one of :data:`DEVICES`)."""
    if kind not in _DEVICE_CLASSES:
        raise ValueError(f"unknown fake device {kind!r}; choose one of {DEVICES}")
    return _DEVICE_CLASSES[kind](world)


# ============================================================================ TCP server
class FakeServer:
    """TCP servers on ``host`` bridging sockets to devices of one world (one client each at a time).

    Attributes:
        urls: ``{device: "socket://host:port"}``.
    """

    def __init__(self, world: FakeRig, devices=("grbl", "level"), host: str = "127.0.0.1", ports=None,
                 stream_interval_s: float = 0.01) -> None:
        self.world, self.host, self.stream_interval_s = world, host, float(stream_interval_s)
        self.urls: dict[str, str] = {}
        self._stop = threading.Event()
        self._threads = []
        self._sockets = []
        ports = dict(ports or {})
        for kind in devices:
            srv = socket.create_server((host, int(ports.get(kind, 0))))
            srv.settimeout(0.05)
            self._sockets.append(srv)
            self.urls[kind] = f"socket://{host}:{srv.getsockname()[1]}"
            thread = threading.Thread(target=self._serve, args=(srv, kind), daemon=True, name=f"fakerig-{kind}")
            thread.start()
            self._threads.append(thread)

    def _serve(self, srv: socket.socket, kind: str) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = srv.accept()
            except (socket.timeout, OSError):
                continue
            with conn:
                conn.settimeout(0.002)
                device = make_device(self.world, kind)
                streaming, device.streaming = device.streaming, False
                last = 0.0
                while not self._stop.is_set() and not device.dead:
                    try:
                        data = conn.recv(4096)
                        if not data:
                            break
                        device.receive(data)
                    except socket.timeout:
                        pass
                    except OSError:
                        break
                    now = time.monotonic()
                    if streaming and now - last >= self.stream_interval_s:
                        device.stream_line()
                        last = now
                    out = device.take(4096, 0.0)
                    try:
                        while out:
                            conn.sendall(out)
                            out = device.take(4096, 0.0)
                    except OSError:
                        break

    def close(self) -> None:
        self._stop.set()
        for s in self._sockets:
            s.close()
        for t in self._threads:
            t.join(timeout=1.0)

    def __enter__(self) -> "FakeServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve(world: FakeRig, devices=("grbl", "level"), host: str = "127.0.0.1", ports=None) -> FakeServer:
    """Start :class:`FakeServer` for ``world``; ``server.urls`` holds the ``socket://`` URLs."""
    return FakeServer(world, devices, host, ports)


def main(argv=None) -> None:
    """``python -m dipnet.rig.fake MESH [--radius R] [--devices grbl,level] [--port P]``."""
    parser = argparse.ArgumentParser(description="Serve a fake dipping rig over TCP (socket:// URLs).")
    parser.add_argument("mesh", help="mesh file of the object")
    parser.add_argument("--radius", type=float, default=40.0, help="object radius (mm)")
    parser.add_argument("--devices", default="grbl,level", help=f"comma-separated, from {','.join(DEVICES)}")
    parser.add_argument("--port", type=int, default=0, help="first TCP port (0: any free ports)")
    parser.add_argument("--latency", type=float, default=0.0, help="reply latency (s)")
    parser.add_argument("--move-s", type=float, default=0.0, help="duration of every move (s)")
    args = parser.parse_args(argv)
    kinds = [k.strip() for k in args.devices.split(",") if k.strip()]
    ports = {k: (args.port + i if args.port else 0) for i, k in enumerate(kinds)}
    world = FakeRig(args.mesh, radius=args.radius, latency_s=args.latency, move_s=args.move_s)
    with serve(world, kinds, ports=ports) as server:
        for kind, url in server.urls.items():
            print(f"{kind}: {url}", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
