"""Adaptive scanning on a rig: the planning loop of :mod:`dipnet.adaptive` driving a :class:`ScanRunner`.

Each step extends the scan plan by the planner's batch and runs the runner on it, which dips
only the new orientations (it resumes after the last complete one); the raw scan file then
holds every dip so far and is preprocessed into the loop's measurement.

Resuming
--------
The plan is never stored apart from the scan: every dip that was started is recorded in the
raw scan file with its rig angles, and every later direction is re-derived. Running the same
scan again replays the loop: a step whose dips are all complete in the file is not dipped
again but read back (only the first ``n`` dips of the file, exactly the data that step had),
so the reconstructions and plans repeat bit for bit (the planner is seeded) and the loop
continues where it stopped. A replayed plan that differs from the recorded angles (the code, the
config or the file changed) stops with :class:`~dipnet.rawscan.RawScanFileError` rather than
mixing two plans in one file.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dipnet.adaptive import AdaptiveResult, AdaptiveSettings, adaptive_loop
from dipnet.grid import Grid
from dipnet.measurement import DipMeasurement
from dipnet.operators import DipOperator, make_operator
from dipnet.orientations import Reach
from dipnet.planning import Planner
from dipnet.preprocess import preprocess
from dipnet.rawscan import RawScan, RawScanFileError, read_rawscan
from dipnet.reconstruction import Reconstruction
from dipnet.rig.runner import ScanPlan, ScanRunner, direction_to_rig

log = logging.getLogger(__name__)

MakeRunner = Callable[[ScanPlan, bool], ScanRunner]


class RigDips:
    """The loop's ``acquire`` on a rig (see the module docstring).

    Args:
        make_runner: ``(plan, home) -> ScanRunner`` writing to :attr:`path` (a fresh controller
            and sensor each time: the runner closes them when it returns).
        protocol: the plan's lowering settings (``start_mm``, ``stop_mm``, ``step_mm``, ...) and
            geometry (``origin_height_mm``, ``pivot_mm``): :class:`ScanPlan` fields except orientations.
        path: the raw scan file.
        to_measurement: raw scan (complete dips only) -> measurement on the reconstruction grid.
    """

    def __init__(self, make_runner: MakeRunner, protocol: dict, path: str | Path,
                 to_measurement: Callable[[RawScan], DipMeasurement]) -> None:
        self.make_runner, self.protocol, self.path = make_runner, dict(protocol), Path(path)
        self.to_measurement = to_measurement
        self.orientations: list[tuple[float, float]] = []
        self.homed = False

    def __call__(self, directions: torch.Tensor) -> DipMeasurement:
        tilt, spin = direction_to_rig(directions)
        self.orientations += [(float(t), float(s)) for t, s in zip(np.round(tilt, 6), np.round(spin, 6))]
        n = len(self.orientations)
        recorded = read_rawscan(self.path) if self.path.is_file() else None
        if recorded is not None:
            check_replay(recorded, self.orientations, self.path)
        if recorded is None or len(recorded.complete_orientations()) < n or \
                sorted(recorded.complete_orientations())[:n] != list(range(n)):
            runner = self.make_runner(ScanPlan(list(self.orientations), **self.protocol), not self.homed)
            self.homed = True
            recorded = runner.run()
        else:
            log.info("dips 0-%d are in %s already: replaying the plan", n - 1, self.path)
        first = [o for o in recorded.orientations if o.complete and o.k < n]
        return self.to_measurement(replace(recorded, orientations=first))


def check_replay(recorded: RawScan, orientations: list[tuple[float, float]], path: Path) -> None:
    """Raise :class:`RawScanFileError` if a recorded dip's angles differ from the replayed plan."""
    for o in recorded.orientations:
        if o.k < len(orientations) and not np.allclose((o.tilt_deg, o.spin_deg), orientations[o.k], atol=1e-6):
            raise RawScanFileError(f"{path}: dip {o.k} was recorded at (tilt, spin) = ({o.tilt_deg}, {o.spin_deg}) "
                                   f"but the adaptive plan now gives {orientations[o.k]}: the planner, its config or "
                                   f"the data changed; use another scan name")


def adaptive_scan(make_runner: MakeRunner, protocol: dict, path: str | Path, grid: Grid, solver, planner: Planner,
                  reach: Reach, settings: AdaptiveSettings) -> AdaptiveResult:
    """Scan adaptively (or resume such a scan) on a rig; reconstructions with ``solver`` on ``grid``.

    Args:
        make_runner, protocol, path: see :class:`RigDips`.
        grid: reconstruction grid of the loop (a coarse one keeps each step quick).
        solver: a :class:`~dipnet.solvers.base.Solver`.
        planner, reach, settings: see :func:`dipnet.adaptive.adaptive_loop` (every planned
            direction is a candidate of ``reach``).
    """
    def to_measurement(raw: RawScan) -> DipMeasurement:
        return preprocess(raw, grid=grid, t_start="metadata")

    def reconstruct(measurement: DipMeasurement) -> tuple[Reconstruction, DipOperator]:
        operator = make_operator(grid, measurement.directions, grid.n)
        return solver.solve(measurement, operator), operator

    return adaptive_loop(RigDips(make_runner, protocol, path, to_measurement), reconstruct, planner, reach, settings)


def adaptive_scan_from_config(cfg, path: str | Path) -> RawScan:
    """``scripts/scan.py +planner=adaptive [+reach=authors_rig]``: the rig, sensor and protocol of the
    scan config (as :func:`~dipnet.rig.runner.scan_from_config`), the loop settings of
    ``cfg.planner`` and the reach of ``cfg.reach`` (default the hemisphere); reconstructions with
    the ``voxel`` solver on a ``cfg.planner.resolution`` grid (default 32) of side ``cfg.planner.extent_mm``
    (default 100 mm): with ``minnorm`` estimates the planner's noise level (their misfit) is model
    error far above the sensor noise and its scores hardly tell candidates apart (see
    :mod:`dipnet.planning`). Returns the raw scan."""
    from hydra.utils import instantiate

    from dipnet.rig.runner import plan_settings, register_fake_rig, runner_from_config
    from dipnet.solvers.voxel import VoxelSolver

    register_fake_rig(cfg)
    protocol = plan_settings(cfg)
    settings_cfg = cfg.planner

    def make_runner(plan: ScanPlan, home: bool) -> ScanRunner:
        return runner_from_config(cfg, plan, path, home=home)

    grid = Grid(int(settings_cfg.get("resolution", 32)), 3, float(settings_cfg.get("extent_mm", 100.0)))
    settings = AdaptiveSettings.from_config(settings_cfg)
    reach = instantiate(cfg.reach) if cfg.get("reach") is not None else Reach()
    adaptive_scan(make_runner, protocol, path, grid, VoxelSolver(progress=False), instantiate(settings_cfg.planner),
                  reach, settings)
    return read_rawscan(path)
