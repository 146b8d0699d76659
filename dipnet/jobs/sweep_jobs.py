"""Sweep jobs under Hydra: a failing job does not stop the sweep, one log line per job, failures listed, and
a sweep never writes into the folder of an earlier one."""

from __future__ import annotations

import logging
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from dipnet.core.console import report
from dipnet.experiments.collect import ERROR_FILE, NoRunsError, collect_runs, find_job_dirs, load_run, problems
from dipnet.experiments.tables import markdown_problems
from dipnet.jobs.options import ConfigError
from dipnet.outputs.summary import headline

log = logging.getLogger(__name__)
T = TypeVar("T")


def guarded_job(task: Callable[[], T], out: str | Path) -> T | None:
    """Run one sweep job so that its failure does not stop the sweep.

    Any exception (also ``SystemExit`` from a CLI error wrapper) is written to
    ``out/error.txt`` (first line: ``Type: message``, then the traceback), logged in one line,
    and ``None`` is returned (Optuna counts it as a failed trial). ``KeyboardInterrupt`` still
    stops everything.
    """
    try:
        return task()
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001 - the point is to keep the sweep going
        message = " ".join(str(exc).split()) or "(no message)"
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / ERROR_FILE).write_text(f"{type(exc).__name__}: {message}\n\n{traceback.format_exc()}")
        log.error("job failed: %s: %s (details in %s)", type(exc).__name__, message, out / ERROR_FILE)
        return None


def check_sweep_dir(sweep_dir: Path, overrides: Sequence[str] = ()) -> None:
    """Raise :class:`~dipnet.jobs.options.ConfigError` when ``sweep_dir`` holds another sweep (Hydra's
    ``multirun.yaml`` or any job): the new jobs would replace its jobs of the same numbers and leave the others
    beside them, and ``scripts/compare.py`` would table both sweeps as one. The same sweep run again (its
    ``multirun.yaml`` holds the same task ``overrides``) is let through: its jobs take the same folders, and
    those with ``output.checkpoint`` resume from their checkpoints. A folder with no job (a sweep that failed
    before its first job, on a bad override, leaves only ``multirun.yaml``) holds nothing to keep: let through."""
    if not sweep_dir.is_dir():
        return
    jobs = find_job_dirs(sweep_dir)
    saved = sweep_dir / "multirun.yaml"
    if not jobs:
        return
    if saved.is_file() and _sweep_overrides(saved) == list(overrides):
        log.info("%s holds this sweep (the same overrides): running it again into the same job folders", sweep_dir)
        return
    raise ConfigError(f"hydra.sweep.dir={sweep_dir} already holds another sweep ({len(jobs)} jobs): give this "
                      "sweep another hydra.sweep.dir, or delete that folder to run it again")


def _sweep_overrides(multirun_yaml: Path) -> list[str] | None:
    """The task overrides (``hydra.overrides.task``) a sweep's ``multirun.yaml`` records, ``None`` if unreadable."""
    try:
        saved = OmegaConf.load(multirun_yaml)
        return [str(o) for o in OmegaConf.select(saved, "hydra.overrides.task", default=None) or []] or None
    except Exception:  # a damaged or foreign file (OmegaConf and yaml raise many types): not this sweep
        return None


class JobLogCallback(Callback):
    """Hydra callback: a sweep into the folder of an earlier sweep is refused before any job
    (:func:`check_sweep_dir`), one log line per finished job of a sweep, and the failures listed after it; a
    sweep with a failed or unfinished job ends with an ``error:`` line and exit code 1.

    Enable with ``hydra/callbacks: job_log`` (``conf/hydra/callbacks/job_log.yaml``). A job whose
    task raised (without :func:`guarded_job`) also gets its ``error.txt`` here.
    """

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            check_sweep_dir(Path(config.hydra.sweep.dir), OmegaConf.select(config, "hydra.overrides.task", default=()))
        except ConfigError as exc:  # Hydra turns a callback's exception into a warning and runs the sweep anyway
            report(f"error: {exc}")
            raise SystemExit(2) from None

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        out = Path(config.hydra.runtime.output_dir)
        num = config.hydra.job.get("num")
        overrides = " ".join(job_return.overrides or [])
        tag = f"job {num}" if num is not None else "job"
        if job_return.status == JobStatus.FAILED:
            exc = job_return._return_value
            if not (out / ERROR_FILE).is_file():
                text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
                (out / ERROR_FILE).write_text(f"{type(exc).__name__}: {' '.join(str(exc).split())}\n\n{text}")
            log.error("%s FAILED [%s]: %s", tag, overrides, exc)
            return
        run = load_run(out)
        if run.status == "ok":
            if num is not None:  # a single run's own "done: ..." line already said it
                log.info("%s done [%s]: %s", tag, overrides, headline(run.metrics))
        else:
            log.warning("%s %s [%s]: %s", tag, run.status, overrides, run.error or "no metrics.json written")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)  # this sweep's jobs only: on_multirun_start refused an earlier one
        try:
            runs = collect_runs(sweep_dir)
        except NoRunsError as exc:
            log.warning("sweep finished: %s", exc)
            return
        bad = problems(runs)
        log.info("sweep finished: %d of %d jobs ok in %s", len(runs) - len(bad), len(runs), sweep_dir)
        for line in markdown_problems(runs, sweep_dir).splitlines()[2:]:
            log.warning("%s", line)
        if not bad:
            return
        if len(bad) < len(runs):
            log.warning("compare the finished ones with: python scripts/compare.py %s", sweep_dir)
        report(f"error: {len(bad)} of {len(runs)} jobs of the sweep in {sweep_dir} failed or did not finish "
               "(listed above, each with its error.txt): the sweep exits 1")
        raise SystemExit(1)  # a script or cluster job that chains the sweep must not take it for a success
