"""The fake rig's world: one simulated tank, stage and object that all its devices share; faults."""

from __future__ import annotations

import math
import threading
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.geometry import RigGeometry, as_geometry
from dipnet.rig.controller import AxisMap, Position
from dipnet.simulator.physics import Tank

DEVICES = ("grbl", "marlin", "level", "modbus", "ad", "sics")
FAULTS = ("drop", "error", "alarm", "reset", "disconnect", "resend", "unstable", "hold", "door", "late_ok",
          "corrupt_status", "split_status", "stall")
#: Stock GRBL 1.1 settings (as read from the firmware, ``tests/data/grbl-traces/t1.log``) with
#: homing enabled; per-axis ``$10N``..``$13N`` are repeated for every status axis.
GRBL_SETTINGS = {0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0,
                 22: 1, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0}
_GRBL_AXIS_SETTINGS = {100: 250.0, 110: 500.0, 120: 10.0, 130: 200.0}
#: Marlin's steps per unit (``M92``): its defaults for X, Y, Z and E; 1/16 microsteps of a 1.8 degree motor driving
#: a rotary axis directly, 8.888... steps per degree (printed ``8.89``), for A, B and C.
MARLIN_STEPS = {"X": 80.0, "Y": 80.0, "Z": 400.0, "A": 3200 / 360, "B": 3200 / 360, "C": 3200 / 360, "E": 500.0}
WORLDS: dict[str, "FakeRig"] = {}

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

    ``stall`` (Marlin; GRBL moves on): the move stops half-way, as a crash or a stall that stall detection caught
    stops it; the firmware says ``echo:endstops hit:`` and its planner keeps the target.
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
        pivot_mm: deprecated shorthand for ``geometry.pivot_mm`` (non-zero overrides it, with a
            ``DeprecationWarning``): give ``geometry=RigGeometry(pivot_mm=...)``.
        geometry: the rig's true geometry (:class:`~dipnet.core.geometry.RigGeometry` or a mapping).
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
        grbl_startup: a startup block (``$N0``) the GRBL board runs after every reset; only its units word is
            modelled: ``"G20"`` makes the moves that follow it inches until a ``G21``.
        marlin_steps: Marlin's steps per unit by axis letter, overriding :data:`MARLIN_STEPS`; the motors move by the
            steps counted divided by :attr:`marlin_motor_steps` (these values at creation): changing
            ``marlin_steps`` later models a wrong ``M92``.
        marlin_offset: Marlin's workspace offset (logical minus machine position) by axis letter, kept over resets:
            an ``M206`` home offset saved in its EEPROM.
        marlin_soft_limits: Marlin's software endstops, ``{letter: (min, max)}`` in machine coordinates: moves are
            clamped to them (``apply_motion_limits``), silently. Stock Marlin has ``Z: (0, 200)``.
        marlin_reports_steps: whether Marlin reports its steps per unit (``False``: ``M92`` answers only ``ok``,
            as Marlin 1.x, and ``M503`` is compiled out).
    """

    def __init__(self, shape, *, radius: float | None = None, tank: Tank | None = None,
                 origin_height_mm: float | None = None, pivot_mm: float = 0.0,
                 geometry: RigGeometry | dict | None = None, axes: AxisMap | dict | None = None,
                 status_axes: str = "XYZAB", level_sigma_mm: float = 0.0, level_quantum_mm: float = 0.001,
                 balance_sigma_g: float = 0.0, balance_quantum_g: float = 0.001, density_g_per_mm3: float = 1e-3,
                 unstable_sigma: float = 0.5, latency_s: float = 0.0, move_s: float = 0.0, keepalive_s: float = 2.0,
                 faults: list[Fault | dict] | None = None, sensor_format: SensorFormat | dict | None = None,
                 seed: int = 0, name: str = "fakerig", grbl_settings: dict | None = None,
                 grbl_startup: str = "", marlin_steps: dict | None = None, marlin_offset: dict | None = None,
                 marlin_soft_limits: dict | None = None, marlin_reports_steps: bool = True) -> None:
        if isinstance(shape, str):
            from dipnet.shapes import load_mesh

            shape = load_mesh(shape, radius=radius)
        self.shape = shape
        self.name = name
        self.tank = tank or Tank.default(3)
        r = float(shape.radius())
        self.origin_height_mm = r + 10.0 if origin_height_mm is None else float(origin_height_mm)
        geometry = as_geometry(geometry)
        if pivot_mm:
            warnings.warn("FakeRig(pivot_mm=...) is deprecated: use geometry=RigGeometry(pivot_mm=...) "
                          "(config: rig.geometry.pivot_mm)", DeprecationWarning, stacklevel=2)
            geometry = geometry.with_values(pivot_mm=float(pivot_mm))
        self.geometry = geometry
        self.created = time.monotonic()
        self.axes = axes if isinstance(axes, AxisMap) else AxisMap.from_config(axes)
        self.status_axes = status_axes.upper()
        for name, value in (("level_sigma_mm", level_sigma_mm), ("level_quantum_mm", level_quantum_mm),
                            ("balance_sigma_g", balance_sigma_g), ("balance_quantum_g", balance_quantum_g),
                            ("latency_s", latency_s), ("move_s", move_s)):
            if not (is_real(value) and 0 <= value < math.inf):  # a negative or NaN sigma gave noise-free readings
                raise ValueError(f"rig.fake.{name} must be a finite number >= 0 (0: none), got {value!r}")
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
        self.grbl_startup = str(grbl_startup).upper()
        self.marlin_steps = {**MARLIN_STEPS, **{str(k).upper(): float(v) for k, v in dict(marlin_steps or {}).items()}}
        self.marlin_motor_steps = dict(self.marlin_steps)  # what the mechanics need: an M92 that differs is wrong
        self.marlin_offset = {str(k).upper(): float(v) for k, v in dict(marlin_offset or {}).items()}
        self.marlin_soft_limits = {str(k).upper(): (float(lo), float(hi))
                                   for k, (lo, hi) in dict(marlin_soft_limits or {}).items()}
        self.marlin_reports_steps = bool(marlin_reports_steps)
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

    def machine_position(self, pos: Position | None = None) -> dict[str, float]:
        """Machine coordinates by status axis letter of ``pos`` (default: where the stage is now)."""
        pos = self.position() if pos is None else pos
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

        The fixed point ``A delta = V(t_start + s + delta)`` of :mod:`dipnet.simulator.physics` is solved
        on a table of ``V`` with ``_TABLE_STEP_MM`` spacing (one exact ``volume_below`` call per
        orientation, so the fake stays fast); the tests check it against
        :func:`dipnet.simulator.physics.solve_dip`.
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
