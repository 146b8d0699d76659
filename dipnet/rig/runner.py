"""The scan runner: dip an object along planned orientations, recording every reading safely.

Per orientation: lift to the safe height, rotate, go to the start height (object clear of the
water), then lower in steps of ``step_mm``; after each step wait until the controller is idle,
settle, read the sensor (averaged, with a stability check) and append the reading to the raw
scan file at once (:class:`~dipnet.core.rawscan_writer.RawScanWriter`, flushed and fsynced). When the
orientation is done it is marked complete and the object is lifted clear.

Running the same scan again resumes after the last complete orientation. On any exception
inside a scan, of any type (a timeout, ``error:N``, ``ALARM``, an unexpected reset, a feed hold,
an unstable sensor, a disconnect, a malformed reply, Ctrl-C, SIGTERM or SIGHUP), the runner
takes the safe-stop path: motion stopped, the protocol resynchronised and the state read back
(:meth:`Controller.settle`); the object is lifted to the safe height only when a status report
confirms a trustworthy position (or after re-homing, if ``rehome_on_fault`` allows it);
every reading recorded so far is kept and :class:`ScanAborted` says in one line what happened
and what the operator must do. When the position was lost (an alarm or reset that loses it, or
the controller's link lost after a move was commanded: the board may have restarted at 0), a
marker file next to the scan (``<scan>.position-lost.json``) makes a resumed run refuse to move
until the machine is homed (``home=true``) or the operator confirms the position
(``confirm_position=true``); a copy beside the controller port's lock
(:func:`~dipnet.rig.controller.rig_position_marker`) does the same for a scan into another file on that rig.

The scan file and the controller and sensor ports are locked while a scan runs: a second scan
on the same file or port fails at once.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
import signal
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import serial
import torch
from tqdm.auto import tqdm

from dipnet.core.orientations import (DIRECTION_SETS, Reach, check_grid_angles, direction_to_rig, distinct_rig_angles,
                                      make_directions)
from dipnet.core.atomic_write import write_atomically
from dipnet.core.counts import is_real
from dipnet.core.rawscan import RawScan, RawScanFileError, ScanHeader
from dipnet.core.rawscan_writer import RawScanWriter, check_resumable
from dipnet.core.warn import log_and_warn
from dipnet.core.memory import MAX_READINGS_PER_DIP
from dipnet.rig.controller import (Controller, MotionHeld, PortBusy, PositionUnknown, RigDisconnected, RigError,
                                   SensorUnstable, rig_position_marker)
from dipnet.core.geometry import GEOMETRY_CONFIG_KEY, RigGeometry
from dipnet.rig.sensors import AveragingSensor, Reading, SensorError

log = logging.getLogger(__name__)

UNITS = {"level_mm": "mm", "mass_g": "g"}


def _write_marker(path: Path, record: dict) -> None:
    """Write a position-lost marker whole or not at all (a temporary file renamed over ``path``): a run killed
    while writing it leaves no marker cut short."""
    write_atomically(path, lambda stream: stream.write(json.dumps(record) + "\n"))


def _read_marker(path: Path) -> dict:
    """A position-lost marker's record; one that cannot be read (cut short by a kill, emptied, edited) still says that
    the position was lost, its reason naming the file: the run moves nothing until it homes or the operator confirms
    the position, which removes the marker (it was: a ``JSONDecodeError`` that even ``home=true`` repeated)."""
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        problem = f"its marker {path} cannot be read: {type(exc).__name__}: {' '.join(str(exc).split())[:120]}"
    else:
        if isinstance(record, dict):
            return record
        problem = f"its marker {path} holds no record: {type(record).__name__}"
    return {"reason": f"unknown: {problem}", "scan": "unknown"}


class ScanAborted(RuntimeError):
    """The scan stopped on a fault; the message is one line and says what was kept."""


class ScanSignal(KeyboardInterrupt):
    """SIGTERM / SIGHUP arrived during a scan (handled like Ctrl-C)."""


SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class on_signals:
    """Context manager: while active, ``signals`` (default SIGTERM and SIGHUP) call
    ``handler(signum, frame)`` (Python handles signals in the main thread only; elsewhere
    nothing changes). A signal the process ignores stays ignored: under ``nohup`` a hangup
    must not end the scan."""

    def __init__(self, handler, signals: tuple = SIGNALS) -> None:
        self.handler, self.signals = handler, signals

    def __enter__(self) -> "on_signals":
        self.saved = {}
        try:
            for sig in self.signals:
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self.saved[sig] = signal.signal(sig, self.handler)
        except ValueError:  # not the main thread
            self.saved = {}
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self.saved.items():
            signal.signal(sig, handler)


def raise_scan_signal(signum, frame) -> None:
    """Signal handler of a running scan: end it like Ctrl-C."""
    raise ScanSignal(f"{signal.Signals(signum).name} received")


def defer_signal(signum, frame) -> None:
    """Signal handler during the safe stop: the stop must finish first."""
    log.warning("%s during the safe stop: finishing the stop first", signal.Signals(signum).name)


def plan_orientations(kind: str = "fibonacci", n: int = 30, tilts=None, spins=None, seed: int = 0,
                      max_tilt_deg: float = 90.0) -> list[tuple[float, float]]:
    """The orientations to dip, as ``(tilt_deg, spin_deg)`` pairs in acquisition order.

    Args:
        kind: ``"grid"`` (every ``tilts`` x ``spins`` pair, tilt-major, as the authors' robot),
            each pose once (a pair that commands an earlier pair's pose, as spin 360 after spin 0, is left
            out with a warning: :func:`~dipnet.core.orientations.distinct_rig_angles`),
            or an orientation set of :func:`~dipnet.core.orientations.make_directions`
            (``fibonacci`` | ``random``) with ``n`` directions, converted to rig angles.
        max_tilt_deg: the rig's mechanical tilt limit (degrees): a set beyond it is kept within it
            (:func:`set_within_tilt`, all ``n`` dips); a grid tilt beyond it is refused
            (:func:`~dipnet.core.orientations.check_grid_angles`).
    """
    if kind == "grid":
        check_grid_angles(tilts, spins, max_tilt_deg)  # a tilt the rig cannot reach is an error, not dropped
        pairs = [(float(t), float(s)) for t in tilts for s in spins]
        kept, repeats = distinct_rig_angles(pairs)
        if repeats:
            named = ", ".join(f"({t:g}, {s:g}) as ({t0:g}, {s0:g})" for (t, s), (t0, s0) in repeats)
            log.warning("orientations=grid: %d of its %d tilts x spins pairs command the pose of an earlier pair "
                        "(spins 360 deg apart are one spin): %s; each pose is dipped once, %d dips", len(repeats),
                        len(pairs), named, len(kept))
        return kept
    if kind not in DIRECTION_SETS:  # was make_directions' "choose fibonacci, random or uniform": no grid, no option
        raise ValueError(f"orientations={kind!r} is not an orientation plan: choose grid (with tilts and spins) or "
                         f"one of {', '.join(DIRECTION_SETS)} (with n_dips); nothing moved")
    tilt, spin = direction_to_rig(set_within_tilt(kind, int(n), seed, max_tilt_deg))
    return [(float(t), float(s)) for t, s in zip(np.round(tilt, 6), np.round(spin, 6))]


def tilt_reach(max_tilt_deg: float) -> Reach:
    """The hemisphere up to the rig's mechanical tilt limit ``max_tilt_deg`` (degrees; at most 90)."""
    return Reach(tilt_range_deg=(0.0, min(float(max_tilt_deg), 90.0)))


def set_within_tilt(kind: str, n: int, seed: int, max_tilt_deg: float) -> torch.Tensor:
    """``n`` directions ``(n, 3)`` of the set ``kind`` tilted at most ``max_tilt_deg`` (degrees) from the
    object's z axis. A fibonacci (or uniform) set reaching beyond is spread over the reachable cap
    instead (:meth:`~dipnet.core.orientations.Reach.uniform`, as ``scripts/reconstruct.py``'s fixed plan
    keeps its dips within the reach), so no dip is dropped; a random set reaching beyond is refused.

    Raises:
        ValueError: ``max_tilt_deg`` not above 0, or a random set beyond it; the message names the option.
    """
    directions = make_directions(kind, n, 3, seed)
    if not float(max_tilt_deg) > 0.0:
        raise ValueError(f"max_tilt_deg={max_tilt_deg:g} leaves no tilt to spread n_dips={n} {kind} directions "
                         "over: give max_tilt_deg in (0, 90], or dip vertically with orientations=grid "
                         "'tilts=[0]' 'spins=[0]'")
    reach = tilt_reach(max_tilt_deg)
    beyond = int((~reach.contains(directions)).sum())
    if beyond == 0:
        return directions
    if kind == "random":
        raise ValueError(f"orientations=random puts {beyond} of its n_dips={n} directions beyond max_tilt_deg="
                         f"{max_tilt_deg:g}: use orientations=fibonacci (spread over the reachable tilts) or a "
                         "larger max_tilt_deg")
    log.info("%d of the n_dips=%d %s directions tilt beyond max_tilt_deg=%g: all %d spread over tilts 0-%g deg",
             beyond, n, kind, max_tilt_deg, n, reach.tilt_range_deg[1])
    return reach.uniform(n)


#: Fewer readings per dip than this give no profile worth the robot's time (one slab or none).
MIN_READINGS_PER_DIP = 4


@dataclass
class ScanPlan:
    """Where and how to dip.

    Attributes:
        orientations: ``(tilt_deg, spin_deg)`` pairs.
        start_mm: lowering position of the first reading (object still clear of the water).
        stop_mm: last lowering position (object fully under water), mm.
        step_mm: lowering step ``d`` (mm).
        safe_mm: lowering position where the object is clear of the water (lifts, rotations).
        settle_s: wait after each step before reading (s).
        retries: extra readings (each after ``settle_s``) when a reading is not stable.
        origin_height_mm: if the rig geometry is calibrated, the height of the object's origin
            over the resting water at ``lower_mm = 0``, untilted; recorded per orientation as
            ``t_start_mm`` (the water line in the object frame at stage 0).
        pivot_mm: deprecated shorthand for ``geometry.pivot_mm`` (non-zero overrides it, with a
            ``DeprecationWarning``): give ``geometry=RigGeometry(pivot_mm=...)``.
        geometry: the rig's calibrated geometry (:class:`~dipnet.core.geometry.RigGeometry`), used
            for ``t_start_mm`` and recorded in the header (``config["rig_geometry"]``).
        max_lower_mm: the deepest lowering (mm) before the object reaches the tank bottom, if
            known (``rig.max_lower_mm``, or the fake rig's tank:
            :meth:`~dipnet.rig.fake.world.FakeRig.deepest_lower_mm`).
        max_lower_source: where ``max_lower_mm`` comes from (for the message).

    Raises:
        ValueError: a plan that cannot be run: steps, a ``safe_mm`` deeper than ``start_mm`` (a larger lowering
            position), a negative ``retries`` or ``settle_s``, a stop below the tank bottom, or more than
            :data:`~dipnet.core.memory.MAX_READINGS_PER_DIP` or fewer than :data:`MIN_READINGS_PER_DIP` readings per
            orientation (the message names the ``protocol`` option and the limit; nothing has moved).
    """

    orientations: list[tuple[float, float]]
    start_mm: float
    stop_mm: float
    step_mm: float
    safe_mm: float = 0.0
    settle_s: float = 0.0
    retries: int = 2
    origin_height_mm: float | None = None
    pivot_mm: float = 0.0
    geometry: RigGeometry = field(default_factory=RigGeometry)
    max_lower_mm: float | None = None
    max_lower_source: str = "rig.max_lower_mm"

    def __post_init__(self) -> None:
        if self.pivot_mm:
            warnings.warn("ScanPlan(pivot_mm=...) is deprecated: use geometry=RigGeometry(pivot_mm=...) "
                          "(config: rig.geometry.pivot_mm)", DeprecationWarning, stacklevel=3)
            self.geometry = self.geometry.with_values(pivot_mm=float(self.pivot_mm))
        self.orientations = [(float(t), float(s)) for t, s in self.orientations]
        for name in ("start_mm", "stop_mm", "step_mm", "safe_mm"):  # step_mm=abc: a TypeError; step_mm=true: 1 mm
            value = getattr(self, name)
            if not is_real(value) or not math.isfinite(value):
                raise ValueError(f"protocol.{name} must be a finite number (mm), got {value!r}; nothing moved")
        if not (self.step_mm > 0 and self.stop_mm > self.start_mm):
            raise ValueError(f"need step_mm > 0 and stop_mm > start_mm, got step {self.step_mm}, "
                             f"start {self.start_mm}, stop {self.stop_mm} (protocol.step_mm, protocol.start_mm, "
                             "protocol.stop_mm, mm); nothing moved")
        if self.origin_height_mm is not None and not math.isfinite(self.origin_height_mm):
            raise ValueError(f"rig.origin_height_mm must be a finite height (mm) or null, "
                             f"got {self.origin_height_mm!r}; nothing moved")
        if not math.isfinite(self.safe_mm) or self.safe_mm > self.start_mm:  # lowering positions grow downward
            raise ValueError(f"protocol.safe_mm={self.safe_mm:g} must be <= protocol.start_mm={self.start_mm:g}: "
                             f"lowering positions grow downward (mm), and the safe position, where the object "
                             f"turns, must be no deeper than the first reading's; nothing moved")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise ValueError(f"protocol.retries must be an integer >= 0 (extra readings when one is not stable), "
                             f"got {self.retries!r}; nothing moved")
        if (isinstance(self.settle_s, bool) or not isinstance(self.settle_s, (int, float))
                or not 0 <= self.settle_s < math.inf):
            raise ValueError(f"protocol.settle_s must be a number of seconds >= 0, got {self.settle_s!r}; "
                             "nothing moved")
        if self.max_lower_mm is not None and self.stop_mm > self.max_lower_mm:
            raise ValueError(f"protocol.stop_mm={self.stop_mm:g} lowers the object onto the tank bottom: at most "
                             f"{self.max_lower_mm:.4g} mm ({self.max_lower_source}); nothing moved")
        n = (self.stop_mm - self.start_mm) / self.step_mm + 1
        if n < MIN_READINGS_PER_DIP:
            raise ValueError(f"protocol.step_mm={self.step_mm:g} plans {math.floor(n + 1e-9):.0f} reading(s) per "
                             f"orientation from start_mm {self.start_mm:g} to stop_mm {self.stop_mm:g}: a dip's "
                             f"profile needs at least {MIN_READINGS_PER_DIP}; use a smaller step; nothing moved")
        if n > MAX_READINGS_PER_DIP:
            raise ValueError(f"protocol.stop_mm={self.stop_mm:g} (start_mm {self.start_mm:g}, step_mm "
                             f"{self.step_mm:g}) plans {n:,.0f} readings per orientation: at most "
                             f"{MAX_READINGS_PER_DIP:,}; nothing moved")

    def stages(self) -> np.ndarray:
        """Lowering positions of the readings, ``(n,)`` mm."""
        n = int(math.floor((self.stop_mm - self.start_mm) / self.step_mm + 1e-9)) + 1
        return self.start_mm + self.step_mm * np.arange(n)

    def t_start(self, tilt_deg: float) -> float | None:
        """Water line (object frame) at stage 0 for this tilt, if the geometry is known."""
        if self.origin_height_mm is None:
            return None
        return float(self.geometry.start_heights(tilt_deg, -self.origin_height_mm))


class ScanRunner:
    """Runs a :class:`ScanPlan` with a connected-or-not controller and sensor.

    Args:
        controller: a :class:`~dipnet.rig.controller.Controller` (connected by :meth:`run`).
        sensor: a sensor or :class:`~dipnet.rig.sensors.AveragingSensor`.
        plan: the scan plan.
        path: the raw scan file (``.jsonl``); resumed if it exists.
        header: scan metadata; its ``config`` gains the plan and the controller's and sensor's
            identity (dialect, URL, axis mapping, sensor settings) unless already there.
        home: home the controller before the first orientation; ``None``: home when the board has
            homing enabled (:meth:`Controller.can_home`, e.g. GRBL ``$22=1``).
        progress: show a progress bar with ETA.
        fsync: fsync the file after every reading (survives power loss; a few ms per reading).
        rehome_on_fault: after a fault that loses the position, home (which lifts the lowering
            axis on a rig homing it upwards) before lifting; otherwise stop without moving.
        confirm_position: the operator has checked the machine position by hand: accept it
            (unlock an alarm with ``$X``, clear a position-lost marker) instead of homing.
    """

    def __init__(self, controller: Controller, sensor, plan: ScanPlan, path: str | Path, header: ScanHeader,
                 home: bool | None = True, progress: bool = True, fsync: bool = True, rehome_on_fault: bool = False,
                 confirm_position: bool = False) -> None:
        self.controller, self.sensor, self.plan = controller, sensor, plan
        self.path = Path(path)
        self.header, self.home, self.progress, self.fsync = header, home, progress, fsync
        self.rehome_on_fault, self.confirm_position = rehome_on_fault, confirm_position
        self.marker = self.path.with_name(self.path.name + ".position-lost.json")
        self.rig_marker = rig_position_marker(controller.url)  # the same, for a scan into another file on this rig
        header.config = {"plan": asdict(plan), "controller": controller.identity(), "sensor": sensor.identity(),
                         GEOMETRY_CONFIG_KEY: plan.geometry.to_dict(), **header.config}
        self.where = "connecting"

    # ------------------------------------------------------------------ public
    def run(self) -> RawScan:
        """Scan (or resume); returns the raw scan. Raises :class:`ScanAborted` on a fault."""
        writer = RawScanWriter(self.path, self.header, resume=True, fsync=self.fsync)
        try:
            self._check_resume(writer.scan)
            first = writer.scan.next_orientation()
            if first >= len(self.plan.orientations):
                log.info("scan %s is already complete", self.path)
                return writer.scan
            with on_signals(raise_scan_signal):
                try:
                    self._scan(writer, first)
                except (RigConfigError, PortBusy):
                    raise  # before any motion: a user error (exit 2), nothing to stop
                except BaseException as exc:  # noqa: BLE001 - every exception ends in the safe stop
                    self._abort(writer, exc)
            return writer.scan
        finally:
            writer.close()
            self.controller.close()
            self.sensor_device().close()

    def check_recorded(self, scan: RawScan) -> None:
        """Raise :class:`RawScanFileError` when ``scan`` (this runner's file, read) was recorded with settings that
        this run's header forbids resuming (:func:`~dipnet.core.rawscan_writer.check_resumable`, the check of
        :meth:`run`'s resume), without connecting the controller or the sensor or opening the file: a replay of
        recorded dips that dips nothing (:class:`~dipnet.rig.adaptive.RigDips`) checks with it."""
        check_resumable(scan, self.header, self.path)

    def sensor_device(self):
        return self.sensor.sensor if isinstance(self.sensor, AveragingSensor) else self.sensor

    # ------------------------------------------------------------------ scanning
    def _check_resume(self, scan: RawScan) -> None:
        """Raise :class:`RawScanFileError` when the file was not written by a scan runner (its header records no
        plan: a simulated or converted recording, whose dips would be merged with this rig's) or a recorded
        orientation is not this run's plan's: the orientation options changed (a Fibonacci set of another size is
        another set of directions, not more of them)."""
        planned = self.plan.orientations
        check_rig_scan(scan, self.path)
        self._warn_metadata_kept(scan.header.metadata or {})
        recorded = scan.header.config["plan"].get("orientations")
        for o in scan.orientations:
            if o.k >= len(planned) or not np.allclose((o.tilt_deg, o.spin_deg), planned[o.k], atol=1e-6):
                now = f"({planned[o.k][0]:g}, {planned[o.k][1]:g})" if o.k < len(planned) else "no orientation"
                size = f"{len(recorded)} orientations" if recorded else "its orientations"
                raise RawScanFileError(
                    f"{self.path}: orientation {o.k} was recorded at (tilt, spin) = ({o.tilt_deg}, {o.spin_deg}), "
                    f"where this run plans {now} ({len(planned)} orientations; the file's plan holds {size}): the "
                    "orientation options (n_dips, orientations, seed, tilts, spins, max_tilt_deg) differ from the "
                    "recorded scan's, and another set's directions are not more of the same: resume with the "
                    "recorded options, or scan into another file")

    def _warn_metadata_kept(self, recorded: dict) -> None:
        """Warn, naming the keys, when this run's header metadata (``+metadata.*``: object name, notes) differs from
        the resumed file's ``recorded`` one: a header is written once, so the file keeps its own and this run's is
        not recorded (it was dropped without a word)."""
        given = self.header.metadata or {}
        changed = sorted(k for k in set(given) | set(recorded) if given.get(k) != recorded.get(k))
        if changed:
            log_and_warn(log, f"{self.path}: resumed with metadata other than its header's ({', '.join(changed)}: "
                              f"the file holds {json.dumps({k: recorded.get(k) for k in changed})}, this run gave "
                              f"{json.dumps({k: given.get(k) for k in changed})}); a header is written once, so the "
                              "file keeps its own: edit its first line to change them, or scan into another file")

    def _scan(self, writer: RawScanWriter, first: int) -> None:
        plan, ctl = self.plan, self.controller
        stages = plan.stages()
        self.where = "connecting"
        ctl.connect()
        self.sensor_device().connect()
        writer.record_session({"first_k": first, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                               "controller": ctl.identity(), "sensor": self.sensor.identity()})
        self._check_board(stages, first)
        self._establish_position()
        total = len(plan.orientations) * len(stages)
        with tqdm(total=total, initial=first * len(stages), desc="scan", unit="reading",
                  disable=not self.progress, dynamic_ncols=True) as bar:
            for k in range(first, len(plan.orientations)):
                tilt, spin = plan.orientations[k]
                self.where = f"orientation {k} (tilt {tilt:g}, spin {spin:g})"
                self._move(lower_mm=plan.safe_mm)
                self._move(tilt_deg=tilt, spin_deg=spin)
                self._move(lower_mm=stages[0])
                t0 = plan.t_start(tilt)
                writer.begin_orientation(k, tilt_deg=tilt, spin_deg=spin,
                                         meta={} if t0 is None else {"t_start_mm": t0})
                for i, stage in enumerate(stages):
                    self.where = f"orientation {k} (tilt {tilt:g}, spin {spin:g}), reading {i} at {stage:g} mm"
                    self._move(lower_mm=float(stage))
                    self._record(writer, float(stage))
                    bar.update()
                self.where = f"the end of orientation {k} (tilt {tilt:g}, spin {spin:g})"
                self._check_not_flat(writer, k)
                writer.complete_orientation()
                self.where = f"the lift after orientation {k}"
                self._move(lower_mm=plan.safe_mm)

    def _check_not_flat(self, writer: RawScanWriter, k: int) -> None:
        """Refuse to complete orientation ``k`` when every one of its readings is the same value: the object
        displaces water on the way down, so a level or mass that never changes is a stuck sensor (or one
        repeating a stale value), or an object that never reached the water, and a dip of zero profile makes
        the reconstruction refuse the whole scan. The readings stay in the file as an incomplete dip, which
        the next run dips again.

        Raises:
            SensorError: the dip's readings are all equal (the message names the value and the stages).
        """
        dip = next(o for o in writer.scan.orientations if o.k == k)
        if dip.n_readings < 2 or np.ptp(dip.values) > 0:
            return
        raise SensorError(f"all {dip.n_readings} readings of orientation {k} are {float(dip.values[0]):g} "
                          f"{UNITS[self.header.quantity]}, from lower {float(dip.stage_mm[0]):g} to "
                          f"{float(dip.stage_mm[-1]):g} mm: the object displaces water as it is lowered, so the "
                          f"sensor is stuck (or repeats a stale value), or the object never reached the water "
                          f"(protocol.stop_mm, rig.origin_height_mm); the dip is not marked complete (a dip of zero "
                          f"profile would make the reconstruction refuse the scan): check the sensor")

    def _check_board(self, stages: np.ndarray, first: int) -> None:
        """Check the moves of orientations ``first``.. as they will be sent (the short way round
        of a wrapping axis included, :meth:`AxisMap.route`) against the board's settings."""
        ctl, plan = self.controller, self.plan
        if self.home is None:
            self.home = ctl.can_home()
        moves = []
        for tilt, spin in plan.orientations[first:]:
            moves += [{"lower": plan.safe_mm}, {"tilt": tilt, "spin": spin}, {"lower": float(stages[0])},
                      {"lower": float(stages[-1])}]
        problems = ctl.check_board(self.home, value_ranges(ctl.axes.route(moves, self._start())),
                                   value_ranges(moves))
        for problem in problems:
            log.error("rig config: %s", problem)
        if problems:
            raise RigConfigError(f"the rig config does not fit the controller {ctl.url}: "
                                 + "; ".join(f"({i}) {p}" for i, p in enumerate(problems, 1)))

    def _start(self) -> dict[str, float]:
        """The rig values the scan's first move starts from: the machine zero after homing, else
        the reported position (read only when an axis wraps, the only case it matters)."""
        axes = self.controller.axes
        named = {"lower": axes.lower, "tilt": axes.tilt, "spin": axes.spin}
        if self.home:
            return {name: axis.from_machine(0.0) for name, axis in named.items()}
        if all(axis.wrap is None for axis in named.values()):
            return {}
        here = self.controller.position()
        return {"lower": here.lower_mm, "tilt": here.tilt_deg, "spin": here.spin_deg}

    def _establish_position(self) -> None:
        """Home, or accept the position, before anything moves (see the module docstring)."""
        ctl = self.controller
        if self.marker.exists():
            previous = _read_marker(self.marker).get("reason", "unknown")
            ctl.position_lost = None  # the marker says more than the controller's own state
            ctl.lose_position(f"the previous run lost the position ({previous})")
        elif self.rig_marker is not None and self.rig_marker.exists():
            previous = _read_marker(self.rig_marker)
            ctl.position_lost = None
            ctl.lose_position(f"a run of the scan {previous.get('scan', 'unknown')} on this rig ({ctl.url}) lost the "
                              f"position ({previous.get('reason', 'unknown')})")
        if self.home:
            self.where = "homing"
            ctl.home()
        elif ctl.position_lost is not None and self.confirm_position:
            log.warning("operator confirmed the position (confirm_position=true) after: %s", ctl.position_lost)
            ctl.confirm_position()
            ctl.settle()
        if ctl.position_lost is not None:
            raise PositionUnknown(ctl.position_lost)
        self._clear_position_lost()

    def _move(self, **target) -> None:
        """Move to ``target`` (rig values), wait until the machine is idle and check that it stands where it was
        sent (:meth:`~dipnet.rig.controller.Controller.check_arrived`): no turn, lowering or reading follows a
        move that ended elsewhere."""
        self.controller.move_to(**target)
        self.controller.wait_idle()
        self.controller.check_arrived()

    def _record(self, writer: RawScanWriter, stage: float) -> None:
        """Read the sensor at lowering position ``stage`` (mm) and record the reading: up to ``retries`` more
        tries while it is not stable or not a finite number (a transducer out of range, as one without an
        echo sending NaN, or a line such as ``1e999 mm``). A last reading that is still not finite is not
        recorded (:class:`SensorError`); a last unstable one is, flagged (:class:`SensorUnstable`)."""
        expected = UNITS[self.header.quantity]
        tries = self.plan.retries + 1
        for attempt in range(tries):
            if self.plan.settle_s:
                time.sleep(self.plan.settle_s)
            reading: Reading = self.sensor.read()
            if reading.unit != expected:
                raise SensorError(f"sensor reports {reading.unit!r}, the scan records {expected!r}")
            if reading.stable and math.isfinite(reading.value):
                writer.append_reading(stage, reading.value, time.time(), [])
                return
        if not math.isfinite(reading.value):
            raise SensorError(f"the sensor gave no finite reading in {tries} tr{'y' if tries == 1 else 'ies'} "
                              f"(last {reading.value:g} {reading.unit}): a sensor out of its range (no echo, "
                              f"overrange) or a garbled value; it was not recorded: check the sensor and run again")
        writer.append_reading(stage, reading.value, time.time(), ["unstable"])
        raise SensorUnstable(f"sensor not stable after {self.plan.retries + 1} readings "
                             f"(last {reading.value:g} {reading.unit})")

    # ------------------------------------------------------------------ faults
    def _abort(self, writer: RawScanWriter, exc: BaseException) -> None:
        kept = sum(o.n_readings for o in writer.scan.orientations)
        done = len(writer.scan.complete_orientations())
        if isinstance(exc, ScanSignal):
            cause = f"interrupted ({exc})"
        elif isinstance(exc, KeyboardInterrupt):
            cause = "interrupted (Ctrl-C)"
        else:
            cause = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        with on_signals(defer_signal, SIGNALS + (signal.SIGINT,)):
            outcome = self._safe_stop()
        raise ScanAborted(f"scan stopped at {self.where}: {cause}; {outcome}; kept {kept} readings "
                          f"({done} complete orientations) in {self.path}; {self._resume_advice()}") \
            from (exc if isinstance(exc, Exception) else None)

    def _resume_advice(self) -> str:
        """What makes the next run work: with the position lost, homing (if the board can) or the
        operator's confirmation; else the same command."""
        ctl = self.controller
        if ctl.position_lost is None:
            return "run the same command again to resume"
        home = "home=true (homing re-establishes the position) or " if ctl.can_home() else ""
        return (f"resume with {home}confirm_position=true once you have checked by hand that the machine stands "
                f"where the controller reports (after a restart: at its zero)")

    def _safe_stop(self) -> str:
        """Stop, read the state back, and lift only to a confirmed position; returns what
        happened, as a status report confirmed it (for the message)."""
        ctl, safe = self.controller, self.plan.safe_mm
        if not ctl.moved:
            return "nothing had moved"
        error: BaseException | None = None
        for attempt in range(3):
            try:
                if attempt and (isinstance(error, RigDisconnected) or ctl.link is None):
                    ctl.reconnect()
                try:
                    ctl.settle()
                except PositionUnknown:
                    if not self.rehome_on_fault:
                        raise
                    log.warning("position lost (%s): re-homing before the lift", ctl.position_lost)
                    ctl.home()
                ctl.move_to(lower_mm=safe)
                ctl.wait_idle()
                here = ctl.position()
                ctl.stop()
                self._clear_position_lost()
                return (f"object lifted: the controller reports lower {round(here.lower_mm, 3) + 0.0:.3f} mm "
                        f"(safe height {safe:g} mm)")
            except PositionUnknown as err:
                self._mark_position_lost(str(err))
                return f"OBJECT NOT LIFTED: the position cannot be trusted ({err}); nothing was moved after the fault"
            except MotionHeld as err:
                return f"OBJECT NOT LIFTED: {err}; then lift the object and run again"
            except (RigError, serial.SerialException, OSError, ValueError) as err:
                error = err
                log.warning("safe stop attempt %d failed: %s", attempt + 1, err)
        if ctl.position_lost is not None:
            self._mark_position_lost(ctl.position_lost)
        return f"COULD NOT LIFT THE OBJECT ({type(error).__name__}: {error}) - check the rig"

    def _mark_position_lost(self, reason: str) -> None:
        """Record beside the scan, and for every scan on this controller's port (:attr:`rig_marker`), that the
        position is lost: a later run, of this scan or another, moves nothing until it homes or the operator
        confirms the position."""
        record = {"reason": reason, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "scan": str(self.path)}
        _write_marker(self.marker, record)
        if self.rig_marker is not None:
            try:
                self.rig_marker.parent.mkdir(parents=True, exist_ok=True)
                _write_marker(self.rig_marker, record)
            except OSError as exc:  # the scan's own marker still holds its resume
                log.warning("could not record the lost position for other scans on %s in %s: %s",
                            self.controller.url, self.rig_marker, exc)

    def _clear_position_lost(self) -> None:
        """The position is trusted again (homed, confirmed, or read back after a lift): drop both markers."""
        self.marker.unlink(missing_ok=True)
        if self.rig_marker is not None:
            self.rig_marker.unlink(missing_ok=True)


def check_rig_scan(scan: RawScan, path: Path) -> None:
    """Raise :class:`RawScanFileError` when ``scan`` (read from ``path``) was not recorded by a scan runner: its header
    records no plan (a simulated or converted recording), so a rig's dips must not be merged into it."""
    if not isinstance(scan.header.config.get("plan"), dict):
        raise RawScanFileError(f"{path}: cannot resume, the file was not recorded by a rig scan (its header records no "
                               f"plan; rig {scan.header.rig!r}): its dips are not this rig's; scan into another file")


def value_ranges(moves: list[dict[str, float | None]]) -> dict[str, tuple[float, float]]:
    """``(min, max)`` per axis name of the values that ``moves`` set (``None``: not moved) (pure)."""
    values: dict[str, list[float]] = {}
    for move in moves:
        for name, value in move.items():
            if value is not None:
                values.setdefault(name, []).append(value)
    return {name: (min(v), max(v)) for name, v in values.items()}


class RigConfigError(RigError, ValueError):
    """The rig config does not fit the controller's settings (one message per mismatch)."""
