"""Reconstruct a shape from dip measurements (Hydra entry point).

    python scripts/reconstruct.py                         # built-in shape, simulated dips, minnorm
    python scripts/reconstruct.py solver=implicit n_dips=41
    python scripts/reconstruct.py -m solver=minnorm,voxel n_dips=41,123

Outputs (mesh, volume, measurement, metrics.json, figures) go to the Hydra run directory. A second
job into a directory in use (same ``hydra.run.dir``) is refused with exit code 2 before it writes.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from dipnet.core.console import interrupted
from dipnet.jobs.cli import require_options, run_hydra, user_errors
from dipnet.jobs.sweep_jobs import guarded_job, sweep_resume_hint, unswept_params
from dipnet.core.locks import run_directory_lock
from dipnet.jobs.pipeline import JobResult, run

log = logging.getLogger("dipnet")


def locked_run(cfg: DictConfig, out: Path) -> JobResult:
    """:func:`dipnet.jobs.pipeline.run` holding ``out``, so a second job into the same directory is refused."""
    with run_directory_lock(out):
        return run(cfg, out)


def resume_hint(cfg: DictConfig, out: Path) -> str:
    """How to go on after Ctrl-C: rerun into the same run directory (with a checkpoint the solve resumes); a sweep
    job: the single run that resumes it and the command that finishes the sweep
    (:func:`~dipnet.jobs.sweep_jobs.sweep_resume_hint`)."""
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        return sweep_resume_hint(HydraConfig.get(), bool(cfg.output.get("checkpoint")))
    if cfg.output.get("checkpoint"):
        return (f"rerun the same command with hydra.run.dir={out} to resume the solve from its checkpoint "
                f"(output.checkpoint)")
    return (f"nothing of the solve was kept; to make a long solve resumable, run it with output.checkpoint=true "
            f"(voxel and implicit solvers) and rerun with hydra.run.dir={out} after an interruption")


@hydra.main(version_base="1.3", config_path="pkg://dipnet.conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    out = Path(HydraConfig.get().runtime.output_dir)
    with interrupted(lambda: resume_hint(cfg, out)):
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            # a failed job writes error.txt and returns None (Optuna: failed trial); the sweep goes on
            return guarded_job(lambda: locked_run(cfg, out).metrics.get("chamfer"), out)
        with user_errors():
            require_options(cfg)
            unswept = unswept_params(HydraConfig.get(), cfg)  # a sweep preset run without -m: one job, unsaid
            if unswept:
                log.warning("%s", unswept)
            result = locked_run(cfg, out)
    log.info("outputs written to %s", out)
    return result.metrics.get("chamfer")


if __name__ == "__main__":
    sys.exit(run_hydra(main))
