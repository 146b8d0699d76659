"""Tune options (prior weights by default) by minimising the Chamfer distance of the jobs (Optuna).

Optuna's ask-and-tell interface drives the ordinary pipeline: each trial composes the job's
config (``conf/config.yaml`` with the base overrides and the trial's values, Hydra's compose
API), runs it (:func:`dipnet.jobs.pipeline.run`) into ``<out>/<trial number>``, and tells the
study its Chamfer distance (truth bounding-box diagonals). A job that raises is a failed trial
(its message in ``error.txt``) and the study goes on; a job whose reconstruction is empty is scored
(Chamfer 1, so the sampler avoids its values) but is never the best. Each trial records the job's
consistency verdict (:mod:`dipnet.evaluation.consistency`: does the result explain its own dips?), and
the best trial is the consistent one of lowest Chamfer: a trial that is ``inconsistent`` with its dips
ranks behind every consistent one (on real data, without a truth, that check is all a user has), and
``best.yaml`` names its verdict, and the lowest-Chamfer trial when ranking passed it over
(:func:`best_trial`). Each trial directory holds
``.hydra/config.yaml`` and ``.hydra/overrides.yaml`` like a Hydra sweep job, so
``scripts/compare.py <out>`` tabulates a study. An ``<out>`` that already holds a study is refused
unless this run continues it (:func:`check_out`). Needs the ``sweeps`` extra (``optuna>=3``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from hydra import compose, initialize_config_module
from hydra.errors import InstantiationException
from hydra.utils import instantiate
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
    """One tuned option: a dotted config key, sampled in ``[low, high]`` (log-uniform with ``log``; whole numbers for
    an integer option with whole ends, :func:`whole_number_keys`)."""

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
        if not math.isfinite(low) or not math.isfinite(high):  # an infinite end: no sampler draws from it
            raise ValueError(f"{text!r}: LOW and HIGH must be finite numbers (a range to sample the option from)")
        return cls(key, low, high, log_scale)


#: The prior weights tuned by default.
DEFAULT_PARAMS = (Param("solver.priors.tv.weight", 1e-4, 1.0), Param("solver.priors.binary.weight", 1e-4, 1.0))


def compose_job(overrides: Sequence[str]) -> DictConfig:
    """The job config of ``conf/config.yaml`` with ``overrides`` (Hydra's compose API)."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def whole_number_keys(params: Sequence[Param], overrides: Sequence[str]) -> set[str]:
    """The tuned options drawn as whole numbers (Optuna's ``suggest_int``): both ends of the range whole and the
    option an integer in the job's config (``n_dips=5:50``, ``resolution``, ``solver.iterations``); a float option
    stays a float whatever its range (``solver.priors.tv.weight=1:10``)."""
    whole = [p for p in params if float(p.low).is_integer() and float(p.high).is_integer()]
    if not whole:
        return set()
    job = compose_job([*BASE_OVERRIDES, *overrides])
    values = {p.key: OmegaConf.select(job, p.key, default=None, throw_on_missing=False) for p in whole}
    return {key for key, value in values.items() if isinstance(value, int) and not isinstance(value, bool)}


def _save_job_config(cfg: DictConfig, overrides: list[str], out: Path) -> None:
    """``.hydra/config.yaml`` and ``.hydra/overrides.yaml``, where a sweep job has them."""
    (out / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out / ".hydra" / "config.yaml")
    OmegaConf.save(OmegaConf.create(list(overrides)), out / ".hydra" / "overrides.yaml")


@dataclass(frozen=True)
class TrialResult:
    """What a trial's job gave: its Chamfer distance (``nan`` when it has none: no truth, or a truth too small
    for the grid), whether its reconstruction is empty (scored Chamfer 1), and its consistency verdict
    (``"consistent"``, ``"inconsistent"``; ``None`` when the job records none) with the check's findings."""

    chamfer: float
    empty: bool
    consistency: str | None = None
    findings: tuple[str, ...] = ()


def run_trial(overrides: list[str], out: Path) -> TrialResult:
    """Run one job into ``out`` and return what the study needs of it (:class:`TrialResult`)."""
    cfg = compose_job(overrides)
    _save_job_config(cfg, overrides, out)
    metrics = run(cfg, out).metrics
    chamfer = metrics.get("chamfer")
    return TrialResult(math.nan if chamfer is None else float(chamfer), bool(metrics.get("empty")),
                       metrics.get("consistency"), tuple(str(w) for w in metrics.get("consistency_warnings") or ()))


class NoBestTrialError(RuntimeError):
    """A study has no trial to recommend: every trial failed or reconstructed nothing."""


def scored_trials(study: Any, out: Path) -> list[Any]:
    """The finished trials whose reconstruction is not empty (``optuna`` ``FrozenTrial`` objects).

    Raises:
        NoBestTrialError: every trial failed (``error.txt`` in its folder) or reconstructed nothing.
    """
    complete = [t for t in study.trials if t.state.name == "COMPLETE"]
    scored = [t for t in complete if not t.user_attrs.get("empty")]
    if not complete:
        raise NoBestTrialError(f"every trial failed (see the error.txt files in {out})")
    if not scored:
        raise NoBestTrialError(f"no best options: every trial's reconstruction is empty (Chamfer 1.0 by convention) "
                               f"or failed; widen or move the tuned ranges (--param) and see the trials in {out}")
    return scored


def inconsistent(trial: Any) -> bool:
    """Whether a trial's result does not explain its own dips (its job's consistency verdict; a trial that
    records none, e.g. of a study stored before verdicts were kept, is not held against)."""
    return trial.user_attrs.get("consistency") == "inconsistent"


def best_trial(study: Any, out: Path) -> Any:
    """The best finished trial whose reconstruction is not empty: the consistent trial of lowest Chamfer distance,
    or, when every such trial is ``inconsistent`` with its dips, the one of lowest Chamfer (an ``optuna``
    ``FrozenTrial``).

    A trial inconsistent with its dips ranks behind every consistent one, whatever its Chamfer: a study on a
    simulation picks settings for real data, where no truth scores the result and the consistency check is the
    only judge; options whose result fails it on the simulation of the object give results that fail it there
    too, which no one can tell from wrong ones (:func:`lowest_chamfer_trial` is the trial ranking passed over).

    Raises:
        NoBestTrialError: every trial failed (``error.txt`` in its folder) or reconstructed nothing.
    """
    return min(scored_trials(study, out), key=lambda t: (inconsistent(t), t.value))


def lowest_chamfer_trial(study: Any, out: Path) -> Any:
    """The finished, non-empty trial of lowest Chamfer distance, whatever its consistency verdict."""
    return min(scored_trials(study, out), key=lambda t: t.value)


def trial_summary(trial: Any) -> dict[str, Any]:
    """A trial for ``best.yaml``: its number, Chamfer distance, options, consistency verdict and findings."""
    return {"trial": trial.number, "chamfer": float(trial.value), "params": dict(trial.params),
            "consistency": trial.user_attrs.get("consistency"),
            "consistency_warnings": list(trial.user_attrs.get("consistency_warnings") or [])}


#: A best value within this share of its range (on the range's scale, log or linear) from one of its ends lies at that
#: end: the optimum may lie beyond it.
EDGE_SHARE = 0.05


def range_edges(values: dict[str, float], params: Sequence[Param]) -> dict[str, str]:
    """The tuned options whose value in ``values`` (a trial's ``params``) lies at an end of its range (within
    :data:`EDGE_SHARE` of it, on the range's scale): ``{key: "low" | "high"}``."""
    edges = {}
    for p in params:
        if p.key not in values:
            continue
        scale = math.log if p.log else float
        share = (scale(values[p.key]) - scale(p.low)) / (scale(p.high) - scale(p.low))
        if share <= EDGE_SHARE:
            edges[p.key] = "low"
        elif share >= 1.0 - EDGE_SHARE:
            edges[p.key] = "high"
    return edges


def best_summary(study: Any, out: Path, overrides: Sequence[str], params: Sequence[Param] = ()) -> dict[str, Any]:
    """The contents of ``best.yaml``: the best trial (:func:`best_trial`: :func:`trial_summary`), the study's
    overrides, how many trials ran, failed and were consistent, ``lowest_chamfer`` (that trial's summary)
    when ranking by the consistency verdict passed over a trial of lower Chamfer, and ``at_range_edge``
    (:func:`range_edges` of the tuned ``params``) when a best value lies at an end of its range."""
    best, lowest = best_trial(study, out), lowest_chamfer_trial(study, out)
    failed = sum(t.state.name != "COMPLETE" for t in study.trials)
    summary = {**trial_summary(best), "overrides": [*overrides], "trials": len(study.trials), "failed": failed,
               "consistent_trials": sum(t.user_attrs.get("consistency") == "consistent" for t in study.trials),
               "ranking": "consistent trials first, then the lowest Chamfer distance"}
    if lowest.number != best.number:
        summary["lowest_chamfer"] = trial_summary(lowest)
    edges = range_edges(best.params, params)
    if edges:
        summary["at_range_edge"] = {key: {"end": end, "range": [p.low, p.high], "scale": "log" if p.log else "linear"}
                                    for p in params for key, end in edges.items() if p.key == key}
    return summary


def edge_messages(summary: dict[str, Any]) -> list[str]:
    """A warning for each best value at an end of its tuned range (:func:`best_summary`'s ``at_range_edge``): the
    search ran into the range's edge, so the best may lie beyond it, and these values are the range's end, not an
    optimum."""
    messages = []
    for key, edge in (summary.get("at_range_edge") or {}).items():
        low, high = edge["range"]
        wider = (f", e.g. --param {key}="
                 + (f"{low / 10:g}:{high:g}" if edge["end"] == "low" else f"{low:g}:{high * 10:g}")
                 if edge["scale"] == "log" else " (as far as the option allows)")
        messages.append(f"the best trial's {key} = {summary['params'][key]:g} lies at the {edge['end']} end of its "
                        f"range [{low:g}, {high:g}] ({edge['scale']} scale, within {EDGE_SHARE:.0%} of it): the best "
                        f"value may lie beyond the range; tune again with a range reaching past that end{wider}")
    return messages


def verdict_messages(summary: dict[str, Any], out: Path) -> list[str]:
    """What a user must hear of the best trial's verdict (:func:`best_summary`), one message each: the best trial
    is inconsistent with its dips (no trial was consistent), or a trial of lower Chamfer was ranked behind it for
    being inconsistent."""
    messages = []
    if summary["consistency"] == "inconsistent":
        finding = summary["consistency_warnings"][0] if summary["consistency_warnings"] else "no finding recorded"
        messages.append(f"the best trial {summary['trial']} is inconsistent with its dips ({finding}); no trial of "
                        f"the study is consistent, so on real data these options may give a result that the data "
                        f"check flags too: see {out / str(summary['trial']) / 'metrics.json'}, and tune further "
                        f"(more trials, other --param ranges)")
    lowest = summary.get("lowest_chamfer")
    if lowest is not None:
        messages.append(f"trial {lowest['trial']} has a lower Chamfer distance ({lowest['chamfer']:.5f} against "
                        f"{summary['chamfer']:.5f}) but is inconsistent with its dips, so it ranks behind trial "
                        f"{summary['trial']} ({summary['consistency'] or 'no verdict recorded'}); its options are "
                        f"under lowest_chamfer in "
                        f"{out / 'best.yaml'}")
    return messages


def study_trial_numbers(out: Path) -> list[int]:
    """The trial folders (``<out>/<number>``) a study directory holds."""
    return sorted(int(p.name) for p in out.iterdir() if p.is_dir() and p.name.isdigit()) if out.is_dir() else []


def check_out(out: Path, continued: int) -> None:
    """Raise :class:`~dipnet.jobs.options.ConfigError` when ``out`` holds a study (trial folders or ``best.yaml``)
    that this run does not continue: a run that starts at trial ``continued`` (the trials its ``--storage``
    already holds; 0 for a new study) would overwrite trial folders and ``best.yaml`` of another study and
    leave the rest beside them."""
    trials = study_trial_numbers(out)
    if not trials and not (out / "best.yaml").is_file():
        return
    if continued and max(trials, default=-1) < continued:
        return
    folders = f"{len(trials)} trial folder{'s' * (len(trials) != 1)}"
    raise ConfigError(f"--out {out} already holds a study ({folders}): choose another --out, "
                      "delete that folder, or, if it was made with --storage, continue it with the same --storage "
                      "and --study-name")


def stored_trials(storage: str | None, study_name: str) -> int:
    """How many trials ``storage`` already holds for ``study_name`` (0 in memory or for a new study)."""
    if storage is None:
        return 0
    optuna = optional_import("optuna", extra="sweeps", purpose="tuning (scripts/tune.py)")
    try:
        return len(optuna.load_study(study_name=study_name, storage=storage).trials)
    except KeyError:  # no such study in the storage yet
        return 0


def study_setting(overrides: Sequence[str], params: Sequence[Param]) -> dict[str, list[str]]:
    """What makes the trials of a study comparable: the job overrides (sorted) and the tuned options, each with its
    scale (``key:log`` or ``key:linear``; the ranges may change between runs, e.g. widened past an end)."""
    return {"overrides": sorted(overrides), "tuned": sorted(f"{p.key}:{'log' if p.log else 'linear'}" for p in params)}


def check_resumed_study(study: Any, overrides: Sequence[str], params: Sequence[Param]) -> None:
    """Record the study's setting (:func:`study_setting`) in its storage, or raise
    :class:`~dipnet.jobs.options.ConfigError` when a stored study that this run continues was run with other
    overrides or other tuned options: its trials' Chamfer distances would be ranked with this run's, and
    ``best.yaml`` would name options of a job this run's overrides do not make. A study stored before the setting
    was recorded is continued as it is."""
    setting = study_setting(overrides, params)
    stored = {key: study.user_attrs[key] for key in setting if key in study.user_attrs}
    if stored and stored != setting:
        differ = "; ".join(f"{key}: {stored.get(key)} in the storage, {setting[key]} now"
                           for key in setting if stored.get(key) != setting[key])
        raise ConfigError(f"--storage study {study.study_name!r} was run with other settings ({differ}): its trials' "
                          "Chamfer distances are not comparable with this run's; give the same overrides and --param "
                          "options to continue it, or another --study-name and --out for a new study")
    for key, value in setting.items():
        study.set_user_attr(key, value)


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


def check_shape(job: DictConfig, params: Sequence[Param]) -> None:
    """Build the shape of a simulated ``job`` (the study at the low end of its ranges) once, and raise
    :class:`~dipnet.jobs.options.ConfigError` with why it cannot be built: the option checks do not build it, so a
    bad name, path or a number tuned where a name goes (``--param shape.name=1:2``: ``unknown built-in 3D shape
    1.46``) failed every trial alike, the whole budget spent."""
    if instantiates(job, "source", RecordedSource):
        return
    try:
        instantiate(job.shape, ndim=int(job.ndim))
    except InstantiationException as exc:
        tuned = [f"--param {p.key}={p.low:g}:{p.high:g}" for p in params if p.key.startswith("shape.")]
        raise ConfigError(f"the study's shape cannot be built: {exc.__cause__ or exc}"
                          + (f" (with {', '.join(tuned)} at its low end: a study draws numbers, so tune a numeric "
                             "shape option, or run names as a sweep: scripts/reconstruct.py -m shape.name=a,b)"
                             if tuned else "") + "; every trial would fail alike") from None


def check_study(n_trials: int, params: Sequence[Param], overrides: Sequence[str]) -> None:
    """Raise ``ValueError`` (:class:`~dipnet.jobs.options.ConfigError`, a Hydra error) for a study that cannot
    run: fewer than 1 trial, an override of a tuned option (each trial would replace it without a word), a job
    option out of range or unknown (the overrides and every tuned option
    at its ``low``, then at its ``high``), a job with no ground truth (:func:`check_ground_truth`) or a shape that
    cannot be built (:func:`check_shape`), before any trial
    (else every trial would fail alike)."""
    if isinstance(n_trials, bool) or not isinstance(n_trials, int) or n_trials < 1:
        raise ValueError(f"the number of trials (--trials) must be a positive integer, got {n_trials!r}")
    tuned = {p.key for p in params}
    twice = sorted({p.key for p in params if sum(q.key == p.key for q in params) > 1})
    if twice:  # Optuna draws the first range's value for both, and the job takes the last
        raise ValueError(f"--param {', '.join(twice)} is given more than once: give each tuned option one range")
    for item in overrides:
        key = item.lstrip("+~").partition("=")[0]
        if key in tuned:
            how = ("one of the options tuned by default, without --param" if tuple(params) == DEFAULT_PARAMS
                   else "a --param")
            raise ValueError(f"override {item} sets {key}, which the study tunes ({how}): each trial's value would "
                             "replace it; an option must be either fixed by an override or tuned, not both")
    whole = whole_number_keys(params, overrides)  # n_dips=5:50 drawn as 5, not 5.0 (which the job refuses)

    def ends(end: str) -> list[str]:
        return [f"{p.key}={int(getattr(p, end)) if p.key in whole else getattr(p, end)!r}" for p in params]

    job = compose_job([*BASE_OVERRIDES, *overrides, *ends("low")])
    check_config(job)
    check_ground_truth(job)
    check_shape(job, params)
    try:   # the range's other end: a range running past what the option takes fails every trial drawn there
        check_config(compose_job([*BASE_OVERRIDES, *overrides, *ends("high")]))
    except ValueError as exc:
        ranges = ", ".join(f"{p.key}={p.low:g}:{p.high:g}" for p in params)
        raise ConfigError(f"{exc} (the high end of a tuned range, --param {ranges}: every trial drawn near it would "
                          "fail; narrow the range to the values the option takes)") from None


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
        The ``optuna.Study`` (its best trial: :func:`best_trial`).
    Raises:
        ValueError: ``n_trials`` < 1, ``n_startup_trials`` < 0, an option out of range (:func:`check_study`), or
            an ``out`` holding another study (:func:`check_out`), before any trial.
        NoBestTrialError: every trial failed or reconstructed nothing.
    """
    optuna = optional_import("optuna", extra="sweeps", purpose="tuning (scripts/tune.py)")
    check_study(n_trials, params, overrides)
    if isinstance(n_startup_trials, bool) or not isinstance(n_startup_trials, int) or n_startup_trials < 0:
        raise ValueError(f"n_startup_trials must be a whole number of random trials >= 0 (tune.py --startup-trials), "
                         f"got {n_startup_trials!r}")
    out = Path(out)
    check_out(out, stored_trials(storage, study_name))
    whole = whole_number_keys(params, overrides)
    sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=n_startup_trials)
    study = optuna.create_study(direction="minimize", sampler=sampler, storage=storage, study_name=study_name,
                                load_if_exists=storage is not None)
    check_resumed_study(study, overrides, params)
    for _ in range(n_trials):
        trial = study.ask()
        values = {p.key: trial.suggest_int(p.key, int(p.low), int(p.high), log=p.log) if p.key in whole
                  else trial.suggest_float(p.key, p.low, p.high, log=p.log) for p in params}
        job = [*BASE_OVERRIDES, *overrides, *(f"{k}={v!r}" for k, v in values.items())]
        trial_dir = out / str(trial.number)
        trial_dir.mkdir(parents=True, exist_ok=True)
        try:
            result = run_trial(job, trial_dir)
        except Exception as exc:  # noqa: BLE001 - a failed job is a failed trial, not the end of the study
            (trial_dir / "error.txt").write_text(f"{type(exc).__name__}: {exc}\n")
            log.warning("trial %d failed: %s: %s", trial.number, type(exc).__name__, exc)
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            continue
        if math.isnan(result.chamfer):  # no ground truth to score against (see run_trial)
            (trial_dir / "error.txt").write_text("no Chamfer distance: the job has no ground truth, or one smaller "
                                                 "than its grid resolves (see its log)\n")
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            continue
        record_trial(trial, result)
        study.tell(trial, result.chamfer)
        log.info("trial %d: chamfer %.5f%s with %s", trial.number, result.chamfer, trial_note(result), values)
    summary = best_summary(study, out, overrides, params)
    OmegaConf.save(OmegaConf.create(summary), out / "best.yaml")
    for message in verdict_messages(summary, out):
        (log.warning if summary["consistency"] == "inconsistent" else log.info)("%s", message)
    for message in edge_messages(summary):
        log.warning("%s", message)
    return study


def record_trial(trial: Any, result: TrialResult) -> None:
    """Keep a trial's emptiness and consistency verdict in the study (``user_attrs``: stored with ``--storage``)."""
    trial.set_user_attr("empty", result.empty)
    trial.set_user_attr("consistency", result.consistency)
    trial.set_user_attr("consistency_warnings", list(result.findings))


def trial_note(result: TrialResult) -> str:
    """The words after a trial's Chamfer distance in its log line: empty, or its consistency verdict."""
    if result.empty:
        return " (empty reconstruction)"
    return f" ({result.consistency})" if result.consistency else ""
