"""The pipeline's self-calibration step (config group ``calibration``): a source's recording in, calibrated
measurement, operator and reconstruction out, plus ``rig_calibration.yaml`` and ``self_calibration.json``.

The recording comes from the source's ``record`` (:mod:`dipnet.preprocessing.sources`): the raw scan the
job simulated, or a raw file prepared with the reader's options; its ``finish`` step (the job's
``symmetry``, the reader's interpolation) finishes every trial measurement.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

from dipnet.calibration.model import to_calibration
from dipnet.calibration.self_calibration import SelfCalibrator
from dipnet.core.calibration_file import save_calibration, scan_tank
from dipnet.core.grid import Grid
from dipnet.core.strict_json import write_json
from dipnet.preprocessing.sources import Recording

log = logging.getLogger(__name__)


def self_calibration_job(calibration: SelfCalibrator, recording: Recording, grid: Grid, solver, n_slabs: int,
                         operator_factory: Callable, out: Path):
    """Run ``calibration`` on ``recording`` with ``solver`` and the operators of ``operator_factory(grid,
    directions, n_slabs)``; returns ``(measurement, operator, reconstruction)`` and writes the calibration
    file, the report and the calibrated measurement into ``out``."""
    result = calibration.run(recording, grid, solver, n_slabs, operator_factory)
    raw, report = recording.raw, result.report
    tank = calibration.tank or scan_tank(raw.header) or "unknown"
    save_calibration(to_calibration(result.geometry, report, raw.header.rig, str(tank),
                                    notes=f"self-calibration of {raw.path or 'a simulated scan'}"),
                     out / "rig_calibration.yaml")
    write_json(out / "self_calibration.json", {**report.to_dict(), "history": result.history, "t0_mm": result.t0_mm},
               indent=2)
    result.measurement.save(out / "measurement.npz")
    log.info("self-calibrated rig geometry:\n%s", report.table())
    return result.measurement, operator_factory(grid, result.measurement.directions, n_slabs), result.reconstruction
