"""Adaptive scanning on a rig: the planning loop of :mod:`dipnet.planning.adaptive` driving a :class:`ScanRunner`.

Each step extends the scan plan by the planner's batch and runs the runner on it, which dips
only the new orientations (it resumes after the last complete one); the raw scan file then
holds every dip so far and is preprocessed into the loop's measurement.

Resuming
--------
The plan is never stored apart from the scan: every dip that was started is recorded in the
raw scan file with its rig angles, and every later direction is re-derived. Running the same
scan again replays the loop: a step whose dips are all complete in the file is not dipped
again but read back (only the first ``n`` dips of the file, exactly the data that step had),
so the reconstructions and plans repeat (the planner is seeded) and the loop continues where it
stopped. Repeat up to floating point: another thread count (``OMP_NUM_THREADS``, ``threads=``) or
library version changes the order of sums, and a greedy plan can then pick another candidate
(measured on the planning benchmark: 2% in Chamfer). The file wins: a recorded dip that the
replayed plan would place elsewhere is kept as recorded, with a warning, and planning goes on
from the recorded data. A recorded dip outside the current reach means the config changed; it
stops with :class:`~dipnet.core.rawscan.RawScanFileError` rather than mixing two rigs' plans in one file.
So does a file recorded with other settings (rig geometry, dip protocol, sensor, ...: the header check of a
resumed :class:`~dipnet.rig.runner.ScanRunner`), checked when the file is first read, before any dip is
replayed, even when every dip of the run is recorded already and no runner runs.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dipnet.planning.adaptive import AdaptiveResult, AdaptiveSettings, adaptive_loop, keep_recorded
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import DipOperator, make_operator
from dipnet.core.orientations import Reach
from dipnet.planning.planner import Planner
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import RawScan, read_rawscan
from dipnet.core.reconstruction import Reconstruction
from dipnet.rig.runner import ScanPlan, ScanRunner, check_rig_scan
from dipnet.core.orientations import direction_to_rig

log = logging.getLogger(__name__)

MakeRunner = Callable[[ScanPlan, bool], ScanRunner]


class RigDips:
    """The loop's ``acquire`` on a rig (see the module docstring).

    Args:
        make_runner: ``(plan, home) -> ScanRunner`` writing to :attr:`path` (a fresh controller
            and sensor each time: the runner closes them when it returns); the first time the file is read, one
            more is made for its header only (:meth:`check_header`), never run.
        plan_settings: the :class:`ScanPlan` fields except the orientations: the dip protocol (``start_mm``,
            ``stop_mm``, ``step_mm``, ...), ``origin_height_mm``, ``geometry``, the deepest lowering.
        path: the raw scan file.
        to_measurement: raw scan (complete dips only) -> measurement on the reconstruction grid.
        reach: what the rig reaches now; a recorded dip outside it stops the scan (module docstring).
    """

    def __init__(self, make_runner: MakeRunner, plan_settings: dict, path: str | Path,
                 to_measurement: Callable[[RawScan], DipMeasurement], reach: Reach | None = None) -> None:
        self.make_runner, self.plan_settings, self.path = make_runner, dict(plan_settings), Path(path)
        self.to_measurement, self.reach = to_measurement, reach
        self.orientations: list[tuple[float, float]] = []
        self.homed = False
        self.checked = False  # the recorded header was compared with this run's (once: the settings stay)

    def __call__(self, directions: torch.Tensor) -> DipMeasurement:
        tilt, spin = direction_to_rig(directions)
        planned = [(float(t), float(s)) for t, s in zip(np.round(tilt, 6), np.round(spin, 6))]
        recorded = read_rawscan(self.path) if self.path.is_file() else None
        if recorded is not None:
            check_rig_scan(recorded, self.path)
            if not self.checked:
                self.check_header(recorded, self.orientations + planned)
            planned = keep_recorded(recorded, planned, len(self.orientations), self.reach, self.path)
        self.orientations += planned
        n = len(self.orientations)
        if recorded is None or len(recorded.complete_orientations()) < n or \
                sorted(recorded.complete_orientations())[:n] != list(range(n)):
            runner = self.make_runner(ScanPlan(list(self.orientations), **self.plan_settings), not self.homed)
            self.homed = True
            recorded = runner.run()
        else:
            log.info("dips 0-%d are in %s already: replaying the plan", n - 1, self.path)
        first = [o for o in recorded.orientations if o.complete and o.k < n]
        return self.to_measurement(replace(recorded, orientations=first))

    def check_header(self, recorded: RawScan, orientations: list[tuple[float, float]]) -> None:
        """Raise :class:`~dipnet.core.rawscan.RawScanFileError` when ``recorded`` (the file) was recorded with other
        settings than this run's, as a resumed runner does (:meth:`ScanRunner.check_recorded`, the same message):
        a replay that dips nothing must not read another scan's dips as this one's. The runner is made for its
        header only (``orientations``: ``(tilt_deg, spin_deg)`` of the plan so far) and never run, so nothing
        connects, moves or writes."""
        self.make_runner(ScanPlan(list(orientations), **self.plan_settings), False).check_recorded(recorded)
        self.checked = True


def adaptive_scan(make_runner: MakeRunner, plan_settings: dict, path: str | Path, grid: Grid, solver, planner: Planner,
                  reach: Reach, settings: AdaptiveSettings) -> AdaptiveResult:
    """Scan adaptively (or resume such a scan) on a rig; reconstructions with ``solver`` on ``grid``.

    Args:
        make_runner, plan_settings, path: see :class:`RigDips`.
        grid: reconstruction grid of the loop (a coarse one keeps each step quick).
        solver: a :class:`~dipnet.solvers.base.Solver`.
        planner, reach, settings: see :func:`dipnet.planning.adaptive.adaptive_loop` (every planned
            direction is a candidate of ``reach``).
    """
    def to_measurement(raw: RawScan) -> DipMeasurement:
        return preprocess(raw, grid=grid, t_start="metadata")

    def reconstruct(measurement: DipMeasurement) -> tuple[Reconstruction, DipOperator]:
        operator = make_operator(grid, measurement.directions, grid.n)
        return solver.solve(measurement, operator), operator

    return adaptive_loop(RigDips(make_runner, plan_settings, path, to_measurement, reach), reconstruct, planner, reach,
                         settings)
