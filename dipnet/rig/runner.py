"""The scan runner: dip an object along planned orientations, recording every reading safely.

Per orientation: lift to the safe height, rotate, go to the start height (object clear of the
water), then lower in steps of ``step_mm``; after each step wait until the controller is idle,
settle, read the sensor (averaged, with a stability check) and append the reading to the raw
scan file at once (:class:`~dipnet.rawscan.RawScanWriter`, flushed and fsynced). When the
orientation is done it is marked complete and the object is lifted clear.

Running the same scan again resumes after the last complete orientation. On any fault
(timeout, ``error:N``, ``ALARM``, an unexpected reset banner, an unstable sensor, a disconnect,
Ctrl-C) the runner lifts the object to the safe height, stops the controller, keeps every
reading recorded so far and raises :class:`ScanAborted` with a one-line message.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import serial
import torch
from tqdm.auto import tqdm

from dipnet.orientations import make_directions
from dipnet.rawscan import RawScan, RawScanFileError, RawScanWriter, ScanHeader
from dipnet.rig.calibration_file import TANK_CONFIG_KEY, Calibration, load_calibration
from dipnet.rig.controller import Controller, RigDisconnected, RigError, SensorUnstable
from dipnet.rig.geometry import GEOMETRY_CONFIG_KEY, RigGeometry
from dipnet.rig.sensors import AveragingSensor, Reading, SensorError

log = logging.getLogger(__name__)

UNITS = {"level_mm": "mm", "mass_g": "g"}


class ScanAborted(RuntimeError):
    """The scan stopped on a fault; the message is one line and says what was kept."""


def direction_to_rig(directions) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`~dipnet.orientations.rig_to_direction`: unit "up" vectors ``(K, 3)``
    (upper hemisphere) to ``(tilt_deg (K,), spin_deg (K,))``; spin is 0 for vertical ones."""
    d = np.asarray(torch.as_tensor(directions, dtype=torch.float64).numpy(), dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(d[:, 2], -1.0, 1.0)))
    lateral = np.hypot(d[:, 0], d[:, 1])
    spin = np.where(lateral > 1e-12, np.degrees(np.arctan2(-d[:, 1], d[:, 0])), 0.0)
    return tilt, np.mod(spin, 360.0)


def plan_orientations(kind: str = "fibonacci", n: int = 30, tilts=None, spins=None, seed: int = 0,
                      max_tilt_deg: float = 90.0) -> list[tuple[float, float]]:
    """The orientations to dip, as ``(tilt_deg, spin_deg)`` pairs in acquisition order.

    Args:
        kind: ``"grid"`` (every ``tilts`` x ``spins`` pair, tilt-major, as the authors' robot),
            or an orientation set of :func:`~dipnet.orientations.make_directions`
            (``fibonacci`` | ``random``) with ``n`` directions, converted to rig angles.
        max_tilt_deg: drop directions tilted further than this (a rig's mechanical limit).
    """
    if kind == "grid":
        if not tilts or not spins:
            raise ValueError("a grid plan needs non-empty lists 'tilts' and 'spins' (degrees)")
        pairs = [(float(t), float(s)) for t in tilts for s in spins]
    else:
        tilt, spin = direction_to_rig(make_directions(kind, int(n), 3, seed))
        pairs = [(float(t), float(s)) for t, s in zip(np.round(tilt, 6), np.round(spin, 6))]
    pairs = [p for p in pairs if p[0] <= max_tilt_deg + 1e-9]
    if not pairs:
        raise ValueError(f"no orientation left within max_tilt_deg={max_tilt_deg}")
    return pairs


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
        pivot_mm: distance of the tilt pivot above the object's origin along its axis (mm); a
            shorthand for ``geometry.pivot_mm`` (non-zero overrides it).
        geometry: the rig's calibrated geometry (:class:`~dipnet.rig.geometry.RigGeometry`), used
            for ``t_start_mm`` and recorded in the header (``config["rig_geometry"]``).
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

    def __post_init__(self) -> None:
        if self.pivot_mm:
            self.geometry = self.geometry.with_values(pivot_mm=float(self.pivot_mm))
        self.orientations = [(float(t), float(s)) for t, s in self.orientations]
        if not self.step_mm > 0 or not self.stop_mm > self.start_mm:
            raise ValueError(f"need step_mm > 0 and stop_mm > start_mm, got step {self.step_mm}, "
                             f"start {self.start_mm}, stop {self.stop_mm}")
        if self.safe_mm > self.start_mm:
            raise ValueError(f"safe_mm ({self.safe_mm}) must not be lower than start_mm ({self.start_mm})")

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
        home: home the controller before the first orientation.
        progress: show a progress bar with ETA.
        fsync: fsync the file after every reading (survives power loss; a few ms per reading).
    """

    def __init__(self, controller: Controller, sensor, plan: ScanPlan, path: str | Path, header: ScanHeader,
                 home: bool = True, progress: bool = True, fsync: bool = True) -> None:
        self.controller, self.sensor, self.plan = controller, sensor, plan
        self.path = Path(path)
        self.header, self.home, self.progress, self.fsync = header, home, progress, fsync
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
            try:
                self._scan(writer, first)
            except (RigError, serial.SerialException, OSError, KeyboardInterrupt) as exc:
                self._abort(writer, exc)
            return writer.scan
        finally:
            writer.close()
            self.controller.close()
            self.sensor_device().close()

    def sensor_device(self):
        return self.sensor.sensor if isinstance(self.sensor, AveragingSensor) else self.sensor

    # ------------------------------------------------------------------ scanning
    def _check_resume(self, scan: RawScan) -> None:
        for o in scan.orientations:
            if o.k >= len(self.plan.orientations) or \
                    not np.allclose((o.tilt_deg, o.spin_deg), self.plan.orientations[o.k], atol=1e-6):
                raise RawScanFileError(f"{self.path}: orientation {o.k} was recorded at (tilt, spin) = "
                                       f"({o.tilt_deg}, {o.spin_deg}), not as planned: use another file")

    def _scan(self, writer: RawScanWriter, first: int) -> None:
        plan, ctl = self.plan, self.controller
        stages = plan.stages()
        self.where = "connecting"
        ctl.connect()
        self.sensor_device().connect()
        if self.home:
            self.where = "homing"
            ctl.home()
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
                writer.complete_orientation()
                self.where = f"the lift after orientation {k}"
                self._move(lower_mm=plan.safe_mm)

    def _move(self, **target) -> None:
        self.controller.move_to(**target)
        self.controller.wait_idle()

    def _record(self, writer: RawScanWriter, stage: float) -> None:
        expected = UNITS[self.header.quantity]
        for attempt in range(self.plan.retries + 1):
            if self.plan.settle_s:
                time.sleep(self.plan.settle_s)
            reading: Reading = self.sensor.read()
            if reading.unit != expected:
                raise SensorError(f"sensor reports {reading.unit!r}, the scan records {expected!r}")
            if reading.stable:
                writer.append_reading(stage, reading.value, time.time(), [])
                return
        writer.append_reading(stage, reading.value, time.time(), ["unstable"])
        raise SensorUnstable(f"sensor not stable after {self.plan.retries + 1} readings "
                             f"(last {reading.value:g} {reading.unit})")

    # ------------------------------------------------------------------ faults
    def _abort(self, writer: RawScanWriter, exc: BaseException) -> None:
        kept = sum(o.n_readings for o in writer.scan.orientations)
        done = len(writer.scan.complete_orientations())
        cause = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else \
            f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        lifted = self._safe_stop()
        raise ScanAborted(f"scan stopped at {self.where}: {cause}; {lifted}; kept {kept} readings "
                          f"({done} complete orientations) in {self.path}; run the same command again "
                          f"to resume") from (exc if isinstance(exc, Exception) else None)

    def _safe_stop(self) -> str:
        """Lift to the safe height and stop; returns what happened (for the message)."""
        ctl, safe = self.controller, self.plan.safe_mm
        error: Exception | None = None
        for attempt in range(3):
            try:
                if attempt and (isinstance(error, RigDisconnected) or ctl.link is None):
                    ctl.reconnect()
                ctl.safe_lift(safe)
                try:
                    ctl.stop()
                except RigError:
                    pass
                return f"object lifted to the safe height {safe:g} mm and controller stopped"
            except (RigError, serial.SerialException, OSError) as err:
                error = err
                log.warning("safe lift attempt %d failed: %s", attempt + 1, err)
        return f"COULD NOT LIFT THE OBJECT ({type(error).__name__}: {error}) - check the rig"


# ---------------------------------------------------------------------------- from config
def build_header(cfg: dict[str, Any], controller: Controller, sensor, plan: ScanPlan) -> ScanHeader:
    """The raw scan header from the scan config (the runner adds the rig identity)."""
    rig = cfg.get("rig", {})
    return ScanHeader(
        quantity=sensor.quantity, ndim=3, tank_cross_section_mm2=rig.get("tank_cross_section_mm2"),
        step_mm=float(plan.step_mm), resolution=rig.get("resolution"),
        rig=str(rig.get("name", controller.dialect)),
        config={"scan": cfg},
        metadata=dict(cfg.get("metadata") or {}))


def scan_from_config(cfg, path: str | Path, progress: bool | None = None) -> RawScan:
    """Build the rig from a scan config (``conf/scan.yaml``) and run (or resume) the scan.

    ``cfg.rig`` holds ``controller`` (``_target_``), ``sensor_url``, ``tank_cross_section_mm2``,
    ``geometry`` and optionally ``fake`` (a :class:`~dipnet.rig.fake.FakeRig`, registered under its
    name so the ``fakerig://`` URLs reach it); ``cfg.sensor`` holds ``device`` (``_target_``) and
    ``average``; ``cfg.orientations`` and ``cfg.protocol`` the plan.
    """
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    if cfg.rig.get("fake") is not None:
        instantiate(cfg.rig.fake, _convert_="all").register()
    controller = instantiate(cfg.rig.controller, _convert_="all")
    device = instantiate(cfg.sensor.device, _convert_="all")
    sensor = AveragingSensor(device, **OmegaConf.to_container(cfg.sensor.average, resolve=True))
    geometry = cfg.rig.get("geometry") or {}
    calibration = rig_calibration(cfg.rig)
    plan = ScanPlan(plan_orientations(**OmegaConf.to_container(cfg.orientations, resolve=True)),
                    **OmegaConf.to_container(cfg.protocol, resolve=True),
                    origin_height_mm=geometry.get("origin_height_mm"), pivot_mm=float(geometry.get("pivot_mm", 0.0)),
                    geometry=calibration.geometry if calibration else RigGeometry())
    header = build_header(OmegaConf.to_container(cfg, resolve=True), controller, sensor, plan)
    if calibration is not None:
        header.config.update({TANK_CONFIG_KEY: calibration.tank, "calibration": calibration.to_dict()})
        header.tank_cross_section_mm2 = calibration.geometry.area(header.tank_cross_section_mm2)
    return ScanRunner(controller, sensor, plan, path, header, home=bool(cfg.home),
                      progress=bool(cfg.progress if progress is None else progress), fsync=bool(cfg.fsync)).run()


def rig_calibration(rig_cfg) -> Calibration | None:
    """The calibration file named by ``rig.calibration`` (checked against ``rig.name`` and ``rig.tank``)."""
    path = rig_cfg.get("calibration")
    if not path:
        return None
    return load_calibration(path, rig=str(rig_cfg.get("name")), tank=rig_cfg.get("tank"))
