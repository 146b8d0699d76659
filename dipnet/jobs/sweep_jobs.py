"""Sweep jobs under Hydra: a failing job does not stop the sweep, one log line per job, failures listed, and
a sweep never writes into the folder of an earlier one."""

from __future__ import annotations

import logging
import shlex
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


#: The script a sweep job's resume commands run (the entry point of every sweep of reconstruction jobs).
SCRIPT = "scripts/reconstruct.py"
#: Hydra overrides about launching a sweep, not about its jobs: a single run of one job leaves them out, and
#: the command rerunning the sweep gives ``-m`` and ``hydra.sweep.dir`` itself.
SWEEP_ONLY = ("hydra.mode=", "hydra.sweep.", "hydra.run.", "hydra/launcher", "hydra.launcher.", "hydra/sweeper",
              "hydra.sweeper.")


def _typed(hydra_cfg: Any, key: str) -> list[str]:
    """The overrides under ``key`` of a Hydra config as typed: ``n_slabs=${resolution}`` is not resolved (against
    the Hydra config, where it means nothing) but passed on as it was given."""
    node = OmegaConf.select(hydra_cfg, key, default=None)
    return [str(o) for o in OmegaConf.to_container(node, resolve=False)] if node is not None else []


def command(args: Sequence[str], config_name: str | None = None) -> str:
    """``python scripts/reconstruct.py ARGS`` as a shell line (each argument quoted where the shell needs it:
    ``shape.path=${dipnet_data:...}``), with ``--config-name`` when the job's config is not the default one."""
    named = ["--config-name", config_name] if config_name and config_name != "config" else []
    return " ".join(["python", SCRIPT, *(shlex.quote(str(a)) for a in [*named, *args])])


def job_command(hydra_cfg: Any) -> str:
    """The single run that reruns one sweep job into its own folder (Hydra's ``hydra.run.dir``; a sweep ignores it):
    the job's overrides (``hydra.overrides.task``) and its Hydra overrides but those of the sweep (:data:`SWEEP_ONLY`).
    ``hydra_cfg``: the job's Hydra config (``HydraConfig.get()``)."""
    task, launch = _typed(hydra_cfg, "overrides.task"), _typed(hydra_cfg, "overrides.hydra")
    launch = [o for o in launch if not o.startswith(SWEEP_ONLY)]
    return command([*task, *launch, f"hydra.run.dir={hydra_cfg.runtime.output_dir}"], hydra_cfg.job.get("config_name"))


def job_sweep_dir(hydra_cfg: Any) -> Path:
    """The folder of a job's sweep: ``hydra.sweep.dir`` when it holds the job's folder, else the job folder's parent
    (a ``hydra.sweep.dir`` of ``${now:...}``, resolved again, may name another time than the sweep's)."""
    out = Path(str(hydra_cfg.runtime.output_dir))
    try:
        sweep_dir = Path(str(hydra_cfg.sweep.dir)).absolute()
    except Exception:  # noqa: BLE001 - an interpolation that does not resolve here (OmegaConf raises many types)
        return out.parent
    return sweep_dir if out.absolute().is_relative_to(sweep_dir) else out.parent


def saved_sweep(hydra_cfg: Any) -> DictConfig | None:
    """The Hydra config of a job's sweep as its ``multirun.yaml`` records it (``None`` when it cannot be read)."""
    try:
        return OmegaConf.load(job_sweep_dir(hydra_cfg) / "multirun.yaml").hydra
    except Exception:  # noqa: BLE001 - a missing or damaged file (OmegaConf and yaml raise many types)
        return None


def sweep_command(hydra_cfg: Any, saved: DictConfig) -> str:
    """The command that runs a job's sweep again into the same folder (:func:`check_sweep_dir` lets it through): the
    sweep's overrides as its ``multirun.yaml`` records them (``saved``: :func:`saved_sweep`), ``-m`` and
    ``hydra.sweep.dir``."""
    launch = [o for o in _typed(saved, "overrides.hydra") if not o.startswith(("hydra.mode=", "hydra.sweep.dir="))]
    return command(["-m", *_typed(saved, "overrides.task"), *launch, f"hydra.sweep.dir={job_sweep_dir(hydra_cfg)}"],
                   hydra_cfg.job.get("config_name"))


def sweep_size(saved: DictConfig) -> int | None:
    """How many jobs a sweep run one after another holds: Hydra's basic sweeper over its ``hydra.sweeper.params``
    and overrides, as it splits them, with the basic (sequential) launcher; ``None`` for another sweeper or
    launcher (a parallel one may have run the jobs after a cut one) or overrides that do not parse here."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        if not (str(saved.sweeper._target_).endswith("BasicSweeper")
                and str(saved.launcher._target_).endswith("BasicLauncher")):
            return None
        node = saved.sweeper.get("params")
        params = OmegaConf.to_container(node, resolve=False) if node else {}
        arguments = [f"{k}={v}" for k, v in params.items()] + _typed(saved, "overrides.task")
        batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(arguments), None)
        return sum(len(batch) for batch in batches)
    except Exception:  # noqa: BLE001 - Hydra's parser and an unusual record raise many types: no count
        return None


def unswept_params(hydra_cfg: Any, cfg: DictConfig) -> str | None:
    """The warning for a single run (no ``-m``) whose config sweeps (``hydra.sweeper.params``, set by a sweep preset
    such as ``experiment=dips_sweep``): Hydra ignores those values without ``-m`` and runs one job with the config's
    own value of each; ``None`` in a sweep, without such values, or when the command line sets each of them."""
    node = OmegaConf.select(hydra_cfg, "sweeper.params", default=None)
    if str(hydra_cfg.mode).endswith("MULTIRUN") or not node:  # RunMode.MULTIRUN, or "MULTIRUN" as saved
        return None
    typed = {str(o).lstrip("+~").partition("=")[0] for o in _typed(hydra_cfg, "overrides.task")}
    swept = {k: v for k, v in OmegaConf.to_container(node, resolve=False).items() if k not in typed}
    if not swept:
        return None
    ran = ", ".join(f"{k}={OmegaConf.select(cfg, k, default=None)}" for k in swept)
    values = " ".join(f"{k}={v}" for k, v in swept.items())
    preset = OmegaConf.select(hydra_cfg, "runtime.choices.experiment", default=None)
    source = f"experiment={preset} sweeps {values}" if preset else f"hydra.sweeper.params sweeps {values}"
    return (f"{source} only with -m: this single run ignores that and runs one "
            f"job with {ran}; add -m to run the sweep, or set those options to silence this")


def rest_of_sweep(hydra_cfg: Any, checkpointed: bool) -> str:
    """The hint's words on the rest of a cut job's sweep: which jobs did not start (none after the last job) and
    the command that finishes the sweep (:func:`sweep_command`), ``""`` without the sweep's ``multirun.yaml``."""
    saved = saved_sweep(hydra_cfg)
    if saved is None:
        return ""
    num, size = hydra_cfg.job.get("num"), sweep_size(saved)
    if size is not None and num is not None and num >= size - 1:
        return f". It is the sweep's last job (of {size}): that run finishes the sweep"
    if size is not None and num is not None:
        after = f"Job {num + 1}" if num + 1 == size - 1 else f"Jobs {num + 1}-{size - 1}"
        which = f". {after} of the sweep's {size} did not start: to finish the sweep"
    else:  # another launcher may run jobs side by side: which ones finished is not known here
        which = ". To finish the sweep (its jobs after this one, or those that had not finished)"
    how = "the finished ones and this one from their checkpoints" if checkpointed else "each from the start"
    return (f"{which}, run it again into its folder: {sweep_command(hydra_cfg, saved)} (it runs every job again, "
            f"{how})")


def sweep_resume_hint(hydra_cfg: Any, checkpointed: bool) -> str:
    """How to go on after Ctrl-C cut a sweep job (:func:`~dipnet.core.console.interrupted`): a sweep ignores
    ``hydra.run.dir``, so "rerun the same command with hydra.run.dir=<job>" reran the sweep, every job of it. The
    cut job alone resumes as a single run into its folder (:func:`job_command`; Hydra has no resume of a sweep:
    each job's folder holds its overrides); the jobs after it did not start, and the sweep's own command, with its
    folder (:func:`rest_of_sweep`), runs every job again: the finished ones too, from their checkpoints when
    ``checkpointed`` (``output.checkpoint``), else from the start."""
    out, num = hydra_cfg.runtime.output_dir, hydra_cfg.job.get("num")
    kept = ("its solve resumes from its checkpoint (output.checkpoint)" if checkpointed else
            "nothing of its solve was kept (a sweep with output.checkpoint=true resumes the solves of voxel and "
            "implicit)")
    return (f"sweep job {num} ({out}) was cut: {kept}. A sweep ignores hydra.run.dir; to rerun this job alone, run "
            f"it once into its folder: {job_command(hydra_cfg)}{rest_of_sweep(hydra_cfg, checkpointed)}")


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
