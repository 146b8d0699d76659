"""Collect the jobs of Hydra sweeps: job directories -> :class:`Run` -> flat rows -> aggregates."""

from __future__ import annotations

import json
import logging
import re
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from dipnet.core.counts import is_real
from dipnet.evaluation.metrics import EMPTY_DISTANCE, REFERENCE_VOLUME_TOL

log = logging.getLogger(__name__)

ERROR_FILE = "error.txt"
METRICS_FILE = "metrics.json"
#: A record of a job's log (Hydra's ``<job>.log``) that starts a new entry, and the one line a refused job
#: ends with (:func:`~dipnet.jobs.cli.user_errors`): ``[time][dipnet][ERROR] - error: ...``.
_LOG_RECORD = re.compile(r"^\[[^\]]*\]\[[^\]]*\]\[[A-Z]+\] - ")
_LOG_ERROR = re.compile(r"^\[[^\]]*\]\[[^\]]*\]\[ERROR\] - error: (?P<message>.+)$")
#: The stems of the recordings a run writes (``measurement.npz``, ``rawscan.jsonl``): a recorded
#: source read from one is labelled with its run folder too (``base/measurement``).
RUN_RECORDINGS = ("measurement", "rawscan")
#: Default grouping of :func:`aggregate` (the paper's axes: method x budget x noise).
GROUP_BY = ("solver", "n_dips", "snr_db")
#: Metrics summarised by default, in table order (Chamfer/Hausdorff: truth bbox diagonals;
#: false_positive/false_negative: fractions of voxels; seconds: solver wall time).
METRICS = ("iou", "chamfer", "hausdorff", "volume_error", "false_positive", "false_negative", "seconds")
#: The metrics an empty reconstruction has by convention only: its Chamfer and Hausdorff distances are
#: :data:`~dipnet.evaluation.metrics.EMPTY_DISTANCE` (one truth diagonal), a stand-in for "no surface", not a
#: distance; :func:`aggregate` leaves them out of the means and counts the empty runs instead.
EMPTY_STANDINS = ("chamfer", "hausdorff")
#: Metrics of runs without a ground truth (recorded sources), in table order: the profile residual
#: (relative), the reconstructed / measured volume and the solver wall time.
DATA_METRICS = ("profile_residual", "volume_ratio", "seconds")
LABELS = {"iou": "IoU", "chamfer": "Chamfer", "hausdorff": "Hausdorff", "volume_error": "volume error",
           "false_positive": "false positive", "false_negative": "false negative", "seconds": "seconds",
           "n_dips": "dips", "snr_db": "SNR (dB)", "solver": "solver", "shape": "shape",
           "dips_percent": "% of dips", "series": "solver", "error_1_minus_iou": "1 - IoU",
           "profile_residual": "profile residual", "volume_ratio": "volume ratio"}


class NoRunsError(FileNotFoundError):
    """A directory holds no reconstruction jobs."""


@dataclass
class Run:
    """One job of a sweep as found on disk.

    Attributes:
        path: the job directory.
        status: ``"ok"`` (``metrics.json`` written by this run), ``"failed"`` (``error.txt``, also one written after
            ``metrics.json``: a job that failed after its numbers, e.g. writing its meshes, or a ``tune.py`` trial
            without a Chamfer distance; an unreadable
            ``metrics.json``, or a job log whose last record is an ``error: ...`` line: a refused run) or
            ``"unfinished"`` (none of these: still running, killed, or empty). A ``metrics.json`` an earlier
            run left in the folder (:func:`earlier_metrics`) is not this run's: failed or unfinished.
        config: the job's config as a plain dict (``{}`` when ``.hydra/config.yaml`` is missing).
        overrides: the job's command-line overrides (``.hydra/overrides.yaml``).
        choices: Hydra's config-group choices (``.hydra/hydra.yaml``), e.g. ``{"solver": "lsmr"}``.
        metrics: the contents of ``metrics.json`` (``{}`` unless ``status == "ok"``).
        error: the first line of ``error.txt``, the job log's ``error:`` line, or why ``metrics.json`` is
            unreadable.
    """

    path: Path
    status: str
    config: dict = field(default_factory=dict)
    overrides: list[str] = field(default_factory=list)
    choices: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    error: str | None = None


def _load_yaml(path: Path) -> Any:
    """A YAML file as plain containers, interpolations resolved where possible (``None`` if absent)."""
    if not path.is_file():
        return None
    cfg = OmegaConf.load(path)
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - e.g. ${hydra:...} resolvers outside a Hydra run
        return OmegaConf.to_container(cfg, resolve=False)


def is_job_dir(path: Path) -> bool:
    """Whether ``path`` is a job's run directory: it holds ``.hydra/config.yaml``, ``metrics.json`` or ``error.txt``."""
    return (path / ".hydra" / "config.yaml").is_file() or (path / METRICS_FILE).is_file() \
        or (path / ERROR_FILE).is_file()


def find_job_dirs(root: str | Path) -> list[Path]:
    """Job directories under ``root`` (``root`` itself if it is one), sorted naturally.

    A job directory holds ``.hydra/config.yaml``, ``metrics.json`` or ``error.txt``; a numbered
    sub-directory of a sweep root (the folder with Hydra's ``multirun.yaml``) is a job even when
    empty (it never started).
    """
    root = Path(root)
    if not root.is_dir():
        raise NoRunsError(f"{root}: not a directory")
    if is_job_dir(root):
        return [root]
    found: set[Path] = set()
    for marker in ("config.yaml", METRICS_FILE, ERROR_FILE):
        for p in root.rglob(marker):
            job = p.parent.parent if p.parent.name == ".hydra" else p.parent
            if marker != "config.yaml" or p.parent.name == ".hydra":
                found.add(job)
    for sweep in [root, *(p.parent for p in root.rglob("multirun.yaml"))]:
        if (sweep / "multirun.yaml").is_file():
            found.update(d for d in sweep.iterdir() if d.is_dir() and d.name.isdigit())

    def natural(p: Path) -> list:
        return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in p.relative_to(root).parts]

    return sorted(found, key=natural)


def load_run(job_dir: str | Path) -> Run:
    """Read one job directory (see :class:`Run` for the status rules)."""
    job_dir = Path(job_dir)
    config = _load_yaml(job_dir / ".hydra" / "config.yaml") or {}
    overrides = _load_yaml(job_dir / ".hydra" / "overrides.yaml") or []
    hydra_cfg = _load_yaml(job_dir / ".hydra" / "hydra.yaml") or {}
    choices = (hydra_cfg.get("hydra", {}).get("runtime", {}).get("choices") or {}) \
        if isinstance(hydra_cfg, dict) else {}
    run = Run(job_dir, "unfinished", config, [str(o) for o in overrides], dict(choices))
    metrics_path, error_path = job_dir / METRICS_FILE, job_dir / ERROR_FILE
    if metrics_path.is_file():
        try:
            run.metrics = json.loads(metrics_path.read_text())
            if not isinstance(run.metrics, dict):
                raise ValueError("not a JSON object")
            run.status = "ok"
        except ValueError as exc:
            run.metrics = {}  # a list or number read from the file is no metrics (was an AttributeError in run_row)
            run.status, run.error = "failed", f"unreadable {metrics_path.name}: {exc}"
        if run.status == "ok" and error_path.is_file() and \
                error_path.stat().st_mtime_ns >= metrics_path.stat().st_mtime_ns:
            run.metrics = {}
            run.status, run.error = "failed", (f"{_first_line(error_path)} (written after its metrics.json: the job "
                                               "failed once its numbers were written, so they are not tabled)")
        earlier = earlier_metrics(run) if run.status == "ok" else None
        if earlier is not None:  # the folder's latest run wrote no metrics: refused, killed or still going
            logged = logged_error(job_dir)
            run.metrics = {}
            run.status, run.error = ("failed", f"{logged}; {earlier}") if logged is not None else \
                ("unfinished", f"{earlier}: this run wrote none (still running, or killed)")
    elif error_path.is_file():
        run.status, run.error = "failed", _first_line(error_path)
    else:
        logged = logged_error(job_dir)
        if logged is not None:
            run.status, run.error = "failed", logged
    _warn_non_numeric_metrics(run)
    return run


def _warn_non_numeric_metrics(run: Run) -> None:
    """Warn, naming the run's folder and the value, for every compared metric (:data:`METRICS`) its
    ``metrics.json`` holds as something other than a number or ``null`` (``"0.8"``, ``true``, a list): the
    statistics leave it out, and a column none of whose values is a number drops out of the tables."""
    for name in METRICS:
        value = run.metrics.get(name)
        if value is not None and not is_real(value):
            warnings.warn(f"{run.path}: {METRICS_FILE}'s {name} is {value!r}, not a number: left out of the "
                          f"{LABELS.get(name, name)} column's statistics (a column with no number in any run is "
                          "dropped)", stacklevel=3)


def _first_line(error_path: Path) -> str:
    """The first line of a job's ``error.txt`` (``Type: message``), or that it is empty."""
    lines = error_path.read_text().strip().splitlines()
    return lines[0] if lines else f"{error_path.name} is empty"


def earlier_metrics(run: Run) -> str | None:
    """Why ``run.metrics`` (its ``metrics.json``) are an earlier run's, or ``None``: a run into the folder of
    another (the same ``hydra.run.dir``) writes its ``.hydra/overrides.yaml`` as it starts and its
    ``metrics.json`` only when it finishes, so until then (and for good when it is refused or killed) the folder
    pairs the new run's config with the old run's numbers. The job records the overrides it ran with
    (``overrides`` in ``metrics.json``); they are compared, in any order and as typed (interpolations such as
    ``n_slabs=${resolution}`` unresolved), with ``.hydra/overrides.yaml``.
    Metrics without that record (older runs, :func:`dipnet.jobs.pipeline.run` outside Hydra) are taken as the
    run's."""
    recorded, path = run.metrics.get("overrides"), run.path / ".hydra" / "overrides.yaml"
    if not isinstance(recorded, list) or not path.is_file():
        return None
    recorded = [str(o) for o in recorded]
    typed = [str(o) for o in OmegaConf.to_container(OmegaConf.load(path), resolve=False) or []]  # n_slabs=${resolution}
    if sorted(recorded) == sorted(typed):
        return None
    return (f"its metrics.json is an earlier run's in this folder (overrides: {' '.join(recorded) or 'none'}), "
            f"not this run's ({' '.join(typed) or 'none'})")


def logged_error(job_dir: str | Path) -> str | None:
    """The error a job outside a sweep was refused or stopped with: its log (``<job>.log``, the newest when
    there are several) ending in the ``error: ...`` record of :func:`~dipnet.jobs.cli.user_errors`, as
    ``"<message> (<log name>)"``; ``None`` when no log ends so (a run still going, or killed, logs on)."""
    logs = sorted(Path(job_dir).glob("*.log"), key=lambda p: p.stat().st_mtime)
    if not logs:
        return None
    try:
        text = logs[-1].read_text(errors="replace")
    except OSError:
        return None
    records = [line for line in text.splitlines() if _LOG_RECORD.match(line)]
    found = _LOG_ERROR.match(records[-1]) if records else None
    return f"{found['message']} ({logs[-1].name})" if found else None


def collect_runs(dirs: str | Path | Iterable[str | Path]) -> list[Run]:
    """All jobs under one or several sweep directories (or job directories).

    A job reached twice (a directory given twice, or a sweep and one of its jobs) is read once, with a
    warning naming it: counted twice, it weighted its row's mean and shrank its std.

    Raises:
        NoRunsError: a directory does not exist or holds no job at all.
    """
    dirs = [dirs] if isinstance(dirs, (str, Path)) else list(dirs)
    runs: list[Run] = []
    seen: set[Path] = set()
    repeated: list[Path] = []
    for d in dirs:
        jobs = find_job_dirs(d)
        if not jobs:
            raise NoRunsError(f"{d}: no reconstruction jobs found (no .hydra/config.yaml, metrics.json "
                              f"or error.txt below it); pass the directory of a sweep (`-m`) or of a run")
        for job in jobs:
            key = job.resolve()
            if key in seen:
                repeated.append(job)
                continue
            seen.add(key)
            runs.append(load_run(job))
    if repeated:
        names = ", ".join(map(str, repeated[:3])) + (f" and {len(repeated) - 3} more" if len(repeated) > 3 else "")
        message = (f"{len(repeated)} job(s) were given more than once (the same directory twice, or a sweep and "
                   f"its own jobs): {names}; each is compared once")
        warnings.warn(message, stacklevel=2)
    return runs


def _get(d: dict, dotted: str) -> Any:
    for key in dotted.split("."):
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _shape_label(config: dict) -> str | None:
    """What a run reconstructs: a recorded source's file (its stem; the configured shape is not
    used), else the configured shape's name or mesh file stem."""
    recording = _get(config, "source.reader.path")
    if recording is not None:
        path = Path(str(recording))
        return f"{path.parent.name}/{path.stem}" if path.stem in RUN_RECORDINGS else path.stem
    shape = config.get("shape") or {}
    if not isinstance(shape, dict):
        return str(shape)
    if shape.get("name"):
        return str(shape["name"])
    if shape.get("path"):
        return Path(str(shape["path"])).stem
    return None


def dips_percent(n_dips: int, resolution: int, ndim: int, n_slabs: int | None = None) -> float:
    """``n_dips`` as a percentage of the dips a square system needs (paper Fig. 13a).

    ``N^ndim`` unknowns and ``M`` slabs per dip (``M = N`` by default) need ``N^ndim / M`` dips
    (``N^2`` in 3D, ``N`` in 2D).
    """
    required = resolution ** ndim / (n_slabs or resolution)
    return 100.0 * n_dips / required


def override_values(overrides: Sequence[str]) -> dict[str, Any]:
    """``{key: value}`` of ``key=value`` overrides (``+``/``++`` prefixes dropped, deletions and
    config-group choices such as ``solver=lsmr`` kept as text; numbers parsed), so that swept
    options (``solver.priors.tv.weight=0.01``) become columns."""
    values: dict[str, Any] = {}
    for item in overrides:
        key, sep, text = item.lstrip("+").partition("=")
        if not sep or key.startswith("~") or key.startswith("hydra"):
            continue
        try:
            values[key] = int(text)
        except ValueError:
            try:
                values[key] = float(text)
            except ValueError:
                values[key] = None if text == "null" else text
    return values


def run_row(run: Run, root: Path | None = None) -> dict[str, Any]:
    """One flat row per job: identity (job, status, error), axes (solver, shape, ndim,
    resolution, n_dips, dips_percent, snr_db, seed, overrides) and every scalar metric; ``snr_db`` is
    ``"recorded"`` for a recorded source, whose noise no configured SNR states.

    ``n_dips`` is the number of dips measured (``n_dips_measured`` in ``metrics.json``): with a declared
    ``symmetry`` the job solves its images too (``n_dips`` there, here ``n_dips_with_images``), but a 10-dip run
    with a 4-fold symmetry is a 10-dip run, not one to pool with the 40-dip runs."""
    cfg, m = run.config, run.metrics
    solver = run.choices.get("solver") or m.get("solver")
    if solver is None and isinstance(cfg.get("solver"), dict):
        solver = str(cfg["solver"].get("_target_", "")).rsplit(".", 1)[-1] or None
    snr = m["snr_db"] if "snr_db" in m else cfg.get("snr_db", _get(cfg, "source.simulator.sensor.snr_db"))
    if str(_get(cfg, "source._target_") or "").endswith("RecordedSource"):
        snr = "recorded"  # its noise is the recording's (measured from its readings), not a configured SNR
    row: dict[str, Any] = {
        "job": str(run.path.relative_to(root)) if root is not None and run.path.is_relative_to(root) else str(run.path),
        "status": run.status,
        "solver": solver,
        "shape": m.get("shape") or _shape_label(cfg),
        "ndim": m.get("ndim", cfg.get("ndim")),
        "resolution": m.get("resolution", cfg.get("resolution")),
        "n_dips": m.get("n_dips_measured", m.get("n_dips", cfg.get("n_dips"))),
        "snr_db": snr if snr is None or isinstance(snr, str) else float(snr),
        "seed": cfg.get("seed"),
    }
    if None not in (row["n_dips"], row["resolution"], row["ndim"]):
        row["dips_percent"] = dips_percent(int(row["n_dips"]), int(row["resolution"]), int(row["ndim"]),
                                           cfg.get("n_slabs"))
    if "n_dips" in m and m["n_dips"] != row["n_dips"]:
        row["n_dips_with_images"] = m["n_dips"]
    for key, value in m.items():
        if key not in row and (isinstance(value, (int, float, str)) or value is None):
            row[key] = value
    for key, value in override_values(run.overrides).items():
        row.setdefault(key, value)
    row["overrides"] = " ".join(run.overrides)
    row["error"] = run.error
    return row


#: The columns every row of :func:`run_row` has besides the metrics (the axes a comparison groups by).
ROW_AXES = ("solver", "shape", "ndim", "resolution", "n_dips", "dips_percent", "snr_db", "seed")


def unknown_column_error(rows: Sequence[dict], columns: Sequence[str], flag: str) -> str | None:
    """A message naming the ``columns`` (given with ``flag``, e.g. ``--by``) that no row holds, or ``None``.

    A column no run records is ``None`` in every row: grouping by it pools every run into one row, and a
    montage by it keeps one run per column, with no word. Names what may be given instead: the axes, the
    options the runs set on the command line, and the other columns of ``runs.csv``."""
    known = {k for r in rows for k in r}
    unknown = [c for c in columns if c not in known]
    if not unknown:
        return None
    swept = sorted({k for r in rows for k in override_values(str(r.get("overrides") or "").split())})
    return (f"{flag} {' '.join(unknown)}: no run records {', '.join(map(repr, unknown))}, so every run would fall in "
            f"one group; choose among the axes ({', '.join(ROW_AXES)}), the options the runs set "
            f"({', '.join(swept) or 'none'}) or another column of runs.csv (a metric of metrics.json)")


def run_rows(runs: Sequence[Run], root: str | Path | None = None) -> list[dict[str, Any]]:
    """:func:`run_row` of every run (job paths relative to ``root`` when given)."""
    return [run_row(r, None if root is None else Path(root)) for r in runs]


def _sort_key(value: Any) -> tuple:
    """None last, numbers numerically, anything else as text."""
    if value is None:
        return (2, 0.0, "")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (0, float(value), "")
    return (1, 0.0, str(value))


def aggregate(rows: Sequence[dict], by: Sequence[str] = GROUP_BY,
              metrics: Sequence[str] = METRICS) -> list[dict[str, Any]]:
    """Mean, standard deviation (``ddof=1``; 0 for one run) and count per group of ``ok`` rows.

    Returns one dict per group, sorted by ``by``: the ``by`` keys, ``runs`` (number of ok jobs),
    ``failed`` (how many jobs of the group failed or did not finish, when any did: the means are over the ok jobs
    alone, so a setting that fails on the hard cases would look better than it is without it; a group whose every
    job failed has no row, and the list of failures names it), ``consistent`` (how many of them passed their
    consistency check, when the rows record it),
    ``empty`` (how many reconstructed nothing, when any did) and ``<metric>_mean``, ``<metric>_std`` for
    each metric present in the group (non-finite values are left out of that metric's statistics, and so
    are the :data:`EMPTY_STANDINS` of the empty runs; a metric absent from every row of a group is absent
    from the group's dict).
    """
    groups: dict[tuple, list[dict]] = {}
    failed: dict[tuple, int] = {}
    for row in rows:
        key = tuple(row.get(k) for k in by)
        if row.get("status") == "ok":
            groups.setdefault(key, []).append(row)
        else:
            failed[key] = failed.get(key, 0) + 1
    out = []
    for key in sorted(groups, key=lambda k: tuple(_sort_key(v) for v in k)):
        members = groups[key]
        entry: dict[str, Any] = dict(zip(by, key))
        entry["runs"] = len(members)
        if failed.get(key):  # not in the means: shown beside them
            entry["failed"] = failed[key]
        verdicts = [r.get("consistency") for r in members if r.get("consistency") is not None]
        if verdicts:  # how many runs explain their own data (metrics.json's consistency verdict)
            entry["consistent"] = sum(v == "consistent" for v in verdicts)
        empty = sum(is_empty(r) for r in members)
        if empty:  # shown as a count, not as a Chamfer of 1 in the mean
            entry["empty"] = empty
        for name in metrics:
            values = np.array([float(r[name]) for r in members
                               if isinstance(r.get(name), (int, float)) and not isinstance(r.get(name), bool)
                               and not (name in EMPTY_STANDINS and is_empty(r))])
            values = values[np.isfinite(values)]
            if values.size:
                entry[f"{name}_mean"] = float(values.mean())
                entry[f"{name}_std"] = float(values.std(ddof=1)) if values.size > 1 else 0.0
        out.append(entry)
    return out


def is_empty(row: dict) -> bool:
    """Whether a row's run reconstructed nothing (``empty`` in its ``metrics.json``)."""
    return row.get("empty") is True


def empty_note(rows: Sequence[dict]) -> str:
    """A line on the ok rows whose reconstruction is empty (``""`` when none is): how many, that their Chamfer and
    Hausdorff (:data:`EMPTY_STANDINS`) are left out of the means, and which metrics keep them."""
    ok = [r for r in rows if r.get("status") == "ok"]
    empty = sum(is_empty(r) for r in ok)
    if not empty:
        return ""
    which = "every finished run" if empty == len(ok) else f"{empty} of {len(ok)} finished runs"
    return (f"{which} reconstructed nothing (the empty column): no shape came out of the solve, so their Chamfer and "
            f"Hausdorff ({EMPTY_DISTANCE:.1f} by convention, one truth diagonal) are a stand-in, not a distance, and "
            f"are left out of those means; their IoU (0), volume error (-1) and false rates are in")


#: Last parts of the config options that do not make runs unlike: seeds (replicates of one setting;
#: any option whose name contains ``seed``) and how a run shows or saves itself. The run directory is
#: no config option (it is Hydra's).
UNCHANGING_OPTIONS = ("progress", "figures", "report", "mesh_formats", "checkpoint", "checkpoint_every", "threads")


def flat_config(config: dict, prefix: str = "") -> dict[str, Any]:
    """The leaves of a nested config as ``{"a.b": value}`` (lists as tuples and an empty mapping as ``"{}"``, e.g.
    ``solver.surface_refit={}``, so values compare and hash)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict) and value:
            flat.update(flat_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else "{}" if isinstance(value, dict) \
                else value
    return flat


def _makes_unlike(option: str, top_level: set[str], by: Sequence[str]) -> bool:
    """Whether runs differing in ``option`` are different settings: not a grouping column, a seed, a display
    option, or a nested copy of a top-level option (``planner.n_dips: ${n_dips}``, reported under its own name)."""
    last = option.rsplit(".", 1)[-1]
    return not (option in by or "seed" in last or last in UNCHANGING_OPTIONS
                or ("." in option and last in top_level))


def pooled_options(runs: Sequence[Run], rows: Sequence[dict], by: Sequence[str] = GROUP_BY) -> dict[str, list]:
    """The config options whose values differ between the ok runs pooled into one group of ``by``.

    ``runs`` and their ``rows`` (:func:`run_rows`) in the same order; the solver is compared by its
    config-group choice too. Seeds, display options and the grouping columns are not compared
    (:func:`_makes_unlike`). Returns ``{option: its values in those groups, sorted}`` (``None`` = unset),
    empty when every group holds one setting.
    """
    groups: dict[tuple, list[dict]] = {}
    for run, row in zip(runs, rows):
        if row.get("status") == "ok":
            options = {**flat_config(run.config), "solver": row.get("solver")}
            groups.setdefault(tuple(row.get(k) for k in by), []).append(options)
    varying: dict[str, set] = {}
    for members in groups.values():
        top_level = {k for m in members for k in m if "." not in k}
        for option in {k for m in members for k in m}:
            values = {m.get(option) for m in members}
            if len(values) > 1 and _makes_unlike(option, top_level, by):
                varying.setdefault(option, set()).update(values)
    return {k: sorted(v, key=_sort_key) for k, v in sorted(varying.items())}


def label_series(rows: Sequence[dict], also: str = "snr_db") -> list[dict]:
    """Copies of the rows with a ``series`` label for plotting: the solver, and the value of ``also`` too when
    the ok rows hold more than one: the noise level (``"lsmr @ 30 dB"``, ``"lsmr @ no noise"``) for curves
    against dips, the dips measured (``"lsmr, 41 dips"``) for curves against noise."""
    values = {r.get(also) for r in rows if r.get("status") == "ok"}

    def label(r: dict) -> str:
        value = r.get(also)
        if len(values) < 2:
            return str(r.get("solver"))
        if also == "snr_db":
            return f"{r.get('solver')} @ " + ("no noise" if value is None else f"{value:g} dB")
        return f"{r.get('solver')}, {value} {LABELS.get(also, also)}"

    return [{**r, "series": label(r)} for r in rows]


def curve_groups(rows: Sequence[dict], x: str, metrics: Sequence[str] = METRICS) -> list[dict[str, Any]]:
    """:func:`aggregate` of ``rows`` for a curve of ``metrics`` against ``x``: one ``series`` per solver and,
    when the rows hold several, per value of the other axis (the noise level for ``x`` ``n_dips`` or
    ``dips_percent``, the dips for ``x`` ``snr_db``), so no point pools runs that the summary table keeps apart
    (a 6-dip and a 40-dip run at one SNR are two points, not their mean)."""
    return aggregate(label_series(rows, "n_dips" if x == "snr_db" else "snr_db"), ("series", x), metrics)


def compared_metrics(rows: Sequence[dict]) -> tuple[str, ...]:
    """The metrics to summarise the ok rows on: :data:`METRICS` when every one has a ground truth
    (an ``iou`` entry), :data:`DATA_METRICS` when none has (recorded sources), both when some have."""
    ok = [r for r in rows if r.get("status") == "ok"]
    with_truth = sum("iou" in r for r in ok)
    if with_truth == len(ok):
        return METRICS
    if not with_truth:
        return DATA_METRICS
    return tuple(m for m in METRICS if m not in DATA_METRICS) + DATA_METRICS


def curve_metrics(metrics: Sequence[str]) -> tuple[str, str]:
    """The two metrics of the error-vs-dips curves: IoU and Chamfer when ``metrics`` (from
    :func:`compared_metrics`) has a truth's, else the profile residual and the volume ratio."""
    return ("iou", "chamfer") if "iou" in metrics else ("profile_residual", "volume_ratio")


def truth_note(rows: Sequence[dict]) -> str:
    """A line on the ok rows without a ground truth, and one on those whose IoU reference is approximate
    (``""`` when neither applies). The reference of IoU and the false rates is the true occupancy above the
    run's ``truth_level``; on shapes with faces along the grid axes no level makes it hold the exact volume
    (``truth_binary_volume_error`` beyond :data:`~dipnet.evaluation.metrics.REFERENCE_VOLUME_TOL`), which the
    run's log warns and the tables would not show."""
    ok = [r for r in rows if r.get("status") == "ok"]
    lines = []
    without = sum("iou" not in r for r in ok)
    if without:
        which = "these runs have" if without == len(ok) else f"{without} of {len(ok)} finished runs have"
        lines.append(f"{which} no ground truth (recorded sources), so no IoU or Chamfer: compared on the profile "
                     f"residual, the reconstructed / measured volume ratio and the time")
    errors = [abs(e) for r in ok if isinstance(e := r.get("truth_binary_volume_error"), (int, float))
              and -1.0 < e and abs(e) > REFERENCE_VOLUME_TOL]
    if errors:
        with_truth = sum("iou" in r for r in ok)
        lines.append(f"{len(errors)} of {with_truth} runs with a ground truth have an approximate IoU: their binary "
                     f"reference is up to {max(errors):.1%} off the exact volume (truth_binary_volume_error: faces "
                     f"along the grid axes), so their IoU and false rates are approximate; Chamfer and volume_error "
                     f"use the exact shape")
    return "\n".join(lines)


def problems(runs: Sequence[Run]) -> list[Run]:
    """The failed and unfinished runs."""
    return [r for r in runs if r.status != "ok"]
