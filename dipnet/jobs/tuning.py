"""Tune options (prior weights by default) by minimising the Chamfer distance of the jobs (Optuna).

Optuna's ask-and-tell interface drives the ordinary pipeline: each trial composes the job's
config (``conf/config.yaml`` with the base overrides and the trial's values, Hydra's compose
API), runs it (:func:`dipnet.jobs.pipeline.run`) into ``<out>/<trial number>``, and tells the
study its Chamfer distance (truth bounding-box diagonals). A job that raises is a failed trial
(its message in ``error.txt``) and the study goes on. Each trial directory holds
``.hydra/config.yaml`` and ``.hydra/overrides.yaml`` like a Hydra sweep job, so
``scripts/compare.py <out>`` tabulates a study. Needs the ``sweeps`` extra (``optuna>=3``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from hydra import compose, initialize_config_module
from omegaconf import DictConfig, OmegaConf

from dipnet.core.optional import optional_import
from dipnet.jobs.options import ConfigError, check_config, instantiates
from dipnet.jobs.pipeline import run
from dipnet.preprocessing.sources import RecordedSource
from dipnet.preprocessing.truth import recorded_shape_spec

log = logging.getLogger(__name__)

#: The defaults of a study: the voxel solver at 32^3 from 51 dips, quiet and without figures.
BASE_OVERRIDES = ("solver=voxel", "ndim=3", "resolution=32", "n_dips=51", "output.figures=false",
                  "output.progress=false")


@dataclass(frozen=True)
class Param:
    """One tuned option: a dotted config key, sampled in ``[low, high]`` (log-uniform with ``log``)."""

    key: str
    low: float
    high: float
    log: bool = True

    @classmethod
    def parse(cls, text: str) -> "Param":
        """``"solver.priors.tv.weight=1e-4:1"`` (log-uniform) or ``"key=0:1:linear"``."""
        key, _, bounds = text.partition("=")
        parts = bounds.split(":")
        if not key or len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] not in ("log", "linear")):
            raise ValueError(f"a tuned option is KEY=LOW:HIGH[:log|linear], got {text!r}")
        low, high = float(parts[0]), float(parts[1])
        log_scale = len(parts) == 2 or parts[2] == "log"
        if not low < high or (log_scale and not low > 0):
            raise ValueError(f"{text!r}: need LOW < HIGH (and LOW > 0 on a log scale)")
        return cls(key, low, high, log_scale)


#: The prior weights tuned by default.
DEFAULT_PARAMS = (Param("solver.priors.tv.weight", 1e-4, 1.0), Param("solver.priors.binary.weight", 1e-4, 1.0))


def compose_job(overrides: Sequence[str]) -> DictConfig:
    """The job config of ``conf/config.yaml`` with ``overrides`` (Hydra's compose API)."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _save_job_config(cfg: DictConfig, overrides: list[str], out: Path) -> None:
    """``.hydra/config.yaml`` and ``.hydra/overrides.yaml``, where a sweep job has them."""
    (out / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out / ".hydra" / "config.yaml")
    OmegaConf.save(OmegaConf.create(list(overrides)), out / ".hydra" / "overrides.yaml")


def run_trial(overrides: list[str], out: Path) -> float:
    """Run one job and return its Chamfer distance (``nan`` when it has none: no truth, or a truth
    too small for the grid)."""
    cfg = compose_job(overrides)
    _save_job_config(cfg, overrides, out)
    chamfer = run(cfg, out).metrics.get("chamfer")
    return math.nan if chamfer is None else float(chamfer)


def check_ground_truth(cfg: DictConfig) -> None:
    """Raise :class:`~dipnet.jobs.options.ConfigError` for a job with no ground truth to score: a recorded
    source whose file names no shape (every file but a fake-rig scan, :mod:`dipnet.preprocessing.truth`)."""
    if not instantiates(cfg, "source", RecordedSource):
        return
    path = cfg.source.reader.path
    if recorded_shape_spec(path) is None:
        raise ConfigError(f"source=recorded: {path} has no ground truth, and tuning scores each trial by its "
                          "Chamfer distance to the truth: tune on a simulated source (source=simulated, the "
                          "default) with a shape like the recorded object, e.g. shape=mesh shape.path=<its mesh>, "
                          "then reconstruct the recording with the best options")


def check_study(n_trials: int, params: Sequence[Param], overrides: Sequence[str]) -> None:
    """Raise ``ValueError`` (:class:`~dipnet.jobs.options.ConfigError`, a Hydra error) for a study that cannot
    run: fewer than 1 trial, a job option out of range or unknown (the overrides and every tuned option
    at its ``low``), or a job with no ground truth (:func:`check_ground_truth`), before any trial (else every
    trial would fail alike)."""
    if isinstance(n_trials, bool) or not isinstance(n_trials, int) or n_trials < 1:
        raise ValueError(f"the number of trials (--trials) must be a positive integer, got {n_trials!r}")
    job = compose_job([*BASE_OVERRIDES, *overrides, *(f"{p.key}={p.low!r}" for p in params)])
    check_config(job)
    check_ground_truth(job)


def tune(out: str | Path, n_trials: int = 20, params: Sequence[Param] = DEFAULT_PARAMS,
         overrides: Sequence[str] = (), seed: int = 0, n_startup_trials: int = 8,
         storage: str | None = None, study_name: str = "dipnet_prior_weights") -> Any:
    """Run ``n_trials`` trials (TPE sampler, seeded) and write ``<out>/best.yaml``.

    Args:
        out: the study directory; trial ``i`` runs in ``<out>/<i>``.
        n_trials: trials to run (added to those a ``storage`` already holds).
        params: the tuned options.
        overrides: Hydra overrides of every job, after :data:`BASE_OVERRIDES` (so they win).
        seed: the sampler's seed; n_startup_trials: random trials before TPE models the results.
        storage: an Optuna storage URL (e.g. ``sqlite:///optuna.db``) to resume or share a study.
    Returns:
        The ``optuna.Study``.
    Raises:
        ValueError: ``n_trials`` < 1, or an option out of range (:func:`check_study`), before any trial.
        RuntimeError: every trial failed.
    """
    optuna = optional_import("optuna", extra="sweeps", purpose="tuning (scripts/tune.py)")
    check_study(n_trials, params, overrides)
    out = Path(out)
    sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=n_startup_trials)
    study = optuna.create_study(direction="minimize", sampler=sampler, storage=storage, study_name=study_name,
                                load_if_exists=storage is not None)
    for _ in range(n_trials):
        trial = study.ask()
        values = {p.key: trial.suggest_float(p.key, p.low, p.high, log=p.log) for p in params}
        job = [*BASE_OVERRIDES, *overrides, *(f"{k}={v!r}" for k, v in values.items())]
        trial_dir = out / str(trial.number)
        trial_dir.mkdir(parents=True, exist_ok=True)
        try:
            chamfer = run_trial(job, trial_dir)
        except Exception as exc:  # noqa: BLE001 - a failed job is a failed trial, not the end of the study
            (trial_dir / "error.txt").write_text(f"{type(exc).__name__}: {exc}\n")
            log.warning("trial %d failed: %s: %s", trial.number, type(exc).__name__, exc)
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            continue
        if math.isnan(chamfer):  # no ground truth to score against (see run_trial)
            (trial_dir / "error.txt").write_text("no Chamfer distance: the job has no ground truth, or one smaller "
                                                 "than its grid resolves (see its log)\n")
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            continue
        study.tell(trial, chamfer)
        log.info("trial %d: chamfer %.5f with %s", trial.number, chamfer, values)
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not complete:
        raise RuntimeError(f"every trial failed (see the error.txt files in {out})")
    best = study.best_trial
    OmegaConf.save(OmegaConf.create(
        {"chamfer": float(best.value), "trial": best.number, "params": dict(best.params),
         "overrides": [*overrides], "trials": len(study.trials), "failed": len(study.trials) - len(complete)}),
        out / "best.yaml")
    return study
