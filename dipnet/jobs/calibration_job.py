"""The pipeline's self-calibration step (config group ``calibration``): raw recording in, calibrated
measurement, operator and reconstruction out, plus ``rig_calibration.yaml`` and ``self_calibration.json``.

Simulated sources use the raw scan the job saved (``rawscan.jsonl``); recorded ones are
prepared by :func:`dipnet.preprocessing.recorded.prepare_recording` with the reader's options, and the
job's symmetry step (top-level ``symmetry``) and the reader's interpolation finish every trial
measurement.
"""

from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from dipnet.calibration.model import to_calibration
from dipnet.calibration.self_calibration import self_calibrate
from dipnet.core.grid import Grid
from dipnet.core.rawscan import read_rawscan
from dipnet.core.calibration_file import TANK_CONFIG_KEY, save_calibration
from dipnet.preprocessing.recorded import finish_measurement, prepare_recording

log = logging.getLogger(__name__)
_FINISH_KEYS = ("symmetry", "interpolate")
_READ_ONLY_KEYS = ("_target_", "_partial_", "path", "t_start", "smooth", *_FINISH_KEYS)


class CalibrationConfigError(ValueError):
    """The self-calibration cannot run with this source (the message names the cause)."""


def self_calibration_job(cfg: DictConfig, grid: Grid, solver, out: Path):
    """Run :func:`~dipnet.calibration.self_calibration.self_calibrate` for the job; returns ``(measurement, operator,
    reconstruction)`` and writes the calibration file, the report and the calibrated measurement."""
    opts = cfg.calibration
    n_slabs = cfg.n_slabs or grid.n
    symmetry = OmegaConf.to_container(cfg.symmetry, resolve=True) if cfg.get("symmetry") else None
    factory = instantiate(cfg.operator)
    if cfg.source.kind == "recorded":
        reader = OmegaConf.to_container(cfg.source.reader, resolve=True)
        path = Path(reader["path"])
        if path.suffix not in (".jsonl", ".csv"):
            raise CalibrationConfigError(f"self-calibration needs a raw recording (.jsonl or .csv), not {path}")
        if reader.get("t_start", "geometry") != "geometry":
            raise CalibrationConfigError("self-calibration places the dips with the rig geometry: "
                                         "set source.reader.t_start=geometry")
        raw, initial, _ = prepare_recording(path, **{k: v for k, v in reader.items() if k not in _READ_ONLY_KEYS})
        smooth = bool(reader.get("smooth", True))
        finish = partial(finish_measurement, symmetry=symmetry or reader.get("symmetry"),
                         interpolate=reader.get("interpolate"))
    else:
        raw, initial = read_rawscan(out / "rawscan.jsonl"), None
        finish = partial(finish_measurement, symmetry=symmetry) if symmetry else None
        smooth = bool(cfg.source.simulator.get("smooth", False))
    result = self_calibrate(raw, grid, solver, tuple(opts.params), n_slabs=n_slabs, operator_factory=factory,
                            smooth=smooth, finish=finish, initial=initial, iterations=int(opts.iterations),
                            dip_offset_sigma_mm=opts.get("dip_offset_sigma_mm"), shape=str(opts.shape),
                            gain_solver=instantiate(opts.gain_solver) if opts.get("gain_solver") else None,
                            max_section_change=float(opts.get("max_section_change", 0.2)))
    report = result.report
    tank = opts.get("tank") or raw.header.config.get(TANK_CONFIG_KEY) or "unknown"
    save_calibration(to_calibration(result.geometry, report, raw.header.rig, str(tank),
                                    notes=f"self-calibration of {raw.path or 'a simulated scan'}"),
                     out / "rig_calibration.yaml")
    (out / "self_calibration.json").write_text(json.dumps({**report.to_dict(), "history": result.history,
                                                            "t0_mm": result.t0_mm}, indent=2))
    result.measurement.save(out / "measurement.npz")
    log.info("self-calibrated rig geometry:\n%s", report.table())
    operator = factory(grid, result.measurement.directions, n_slabs)
    return result.measurement, operator, result.reconstruction
