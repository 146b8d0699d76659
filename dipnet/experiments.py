"""Experiments at scale: collect the jobs of Hydra sweeps, aggregate, tabulate and plot them.

A sweep directory (``python scripts/reconstruct.py -m ...``) holds one directory per job; each
finished job wrote the files of :mod:`dipnet.pipeline` (``.hydra/config.yaml``,
``metrics.json``, ``reconstruction.npz``, ...). A job that raised wrote ``error.txt`` instead
of ``metrics.json`` (see :func:`guarded_job`); a job with neither is unfinished.

Pipeline: :func:`collect_runs` (directories -> :class:`Run`) -> :func:`run_rows` (flat dicts,
one per job) -> :func:`aggregate` (mean and spread per solver x n_dips x snr_db) ->
:func:`write_csv` / :func:`markdown_table` / ``plot_*``. :class:`JobLogCallback` logs one line
per finished job and lists the failures at the end of a sweep.
"""

from __future__ import annotations

import csv
import json
import logging
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from hydra.core.utils import JobReturn, JobStatus  # noqa: E402
from hydra.experimental.callback import Callback  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from dipnet.plots import save_figure  # noqa: E402

log = logging.getLogger(__name__)

ERROR_FILE = "error.txt"
METRICS_FILE = "metrics.json"
#: Default grouping of :func:`aggregate` (the paper's axes: method x budget x noise).
GROUP_BY = ("solver", "n_dips", "snr_db")
#: Metrics summarised by default, in table order (Chamfer/Hausdorff: truth bbox diagonals;
#: false_positive/false_negative: fractions of voxels; seconds: solver wall time).
METRICS = ("iou", "chamfer", "hausdorff", "volume_error", "false_positive", "false_negative", "seconds")
LABELS = {"iou": "IoU", "chamfer": "Chamfer", "hausdorff": "Hausdorff", "volume_error": "volume error",
           "false_positive": "false positive", "false_negative": "false negative", "seconds": "seconds",
           "n_dips": "dips", "snr_db": "SNR (dB)", "solver": "solver", "shape": "shape",
           "dips_percent": "% of dips", "series": "solver", "error_1_minus_iou": "1 - IoU"}

T = TypeVar("T")


class NoRunsError(FileNotFoundError):
    """A directory holds no reconstruction jobs."""


@dataclass
class Run:
    """One job of a sweep as found on disk.

    Attributes:
        path: the job directory.
        status: ``"ok"`` (``metrics.json`` written), ``"failed"`` (``error.txt`` or an unreadable
            ``metrics.json``) or ``"unfinished"`` (neither: still running, killed, or empty).
        config: the job's config as a plain dict (``{}`` when ``.hydra/config.yaml`` is missing).
        overrides: the job's command-line overrides (``.hydra/overrides.yaml``).
        choices: Hydra's config-group choices (``.hydra/hydra.yaml``), e.g. ``{"solver": "lsmr"}``.
        metrics: the contents of ``metrics.json`` (``{}`` unless ``status == "ok"``).
        error: the first line of ``error.txt`` (or why ``metrics.json`` is unreadable).
    """

    path: Path
    status: str
    config: dict = field(default_factory=dict)
    overrides: list[str] = field(default_factory=list)
    choices: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    error: str | None = None


# --------------------------------------------------------------------------- collection

def _load_yaml(path: Path) -> Any:
    """A YAML file as plain containers, interpolations resolved where possible (``None`` if absent)."""
    if not path.is_file():
        return None
    cfg = OmegaConf.load(path)
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - e.g. ${hydra:...} resolvers outside a Hydra run
        return OmegaConf.to_container(cfg, resolve=False)


def _is_job_dir(path: Path) -> bool:
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
    if _is_job_dir(root):
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
    choices = (hydra_cfg.get("hydra", {}).get("runtime", {}).get("choices") or {}) if isinstance(hydra_cfg, dict) else {}
    run = Run(job_dir, "unfinished", config, [str(o) for o in overrides], dict(choices))
    metrics_path, error_path = job_dir / METRICS_FILE, job_dir / ERROR_FILE
    if metrics_path.is_file():
        try:
            run.metrics = json.loads(metrics_path.read_text())
            if not isinstance(run.metrics, dict):
                raise ValueError("not a JSON object")
            run.status = "ok"
        except ValueError as exc:
            run.status, run.error = "failed", f"unreadable {metrics_path.name}: {exc}"
    elif error_path.is_file():
        lines = error_path.read_text().strip().splitlines()
        run.status, run.error = "failed", (lines[0] if lines else "error.txt is empty")
    return run


def collect_runs(dirs: str | Path | Iterable[str | Path]) -> list[Run]:
    """All jobs under one or several sweep directories (or job directories).

    Raises:
        NoRunsError: a directory does not exist or holds no job at all.
    """
    dirs = [dirs] if isinstance(dirs, (str, Path)) else list(dirs)
    runs: list[Run] = []
    for d in dirs:
        jobs = find_job_dirs(d)
        if not jobs:
            raise NoRunsError(f"{d}: no reconstruction jobs found (no .hydra/config.yaml, metrics.json "
                              f"or error.txt below it); pass the directory of a sweep (`-m`) or of a run")
        runs.extend(load_run(j) for j in jobs)
    return runs


# --------------------------------------------------------------------------- rows

def _get(d: dict, dotted: str) -> Any:
    for key in dotted.split("."):
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _shape_label(config: dict) -> str | None:
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
    resolution, n_dips, dips_percent, snr_db, seed, overrides) and every scalar metric."""
    cfg, m = run.config, run.metrics
    solver = run.choices.get("solver") or m.get("solver")
    if solver is None and isinstance(cfg.get("solver"), dict):
        solver = str(cfg["solver"].get("_target_", "")).rsplit(".", 1)[-1] or None
    snr = m["snr_db"] if "snr_db" in m else cfg.get("snr_db", _get(cfg, "source.simulator.sensor.snr_db"))
    row: dict[str, Any] = {
        "job": str(run.path.relative_to(root)) if root is not None and run.path.is_relative_to(root) else str(run.path),
        "status": run.status,
        "solver": solver,
        "shape": m.get("shape") or _shape_label(cfg),
        "ndim": m.get("ndim", cfg.get("ndim")),
        "resolution": m.get("resolution", cfg.get("resolution")),
        "n_dips": m.get("n_dips", cfg.get("n_dips")),
        "snr_db": snr if snr is None or isinstance(snr, str) else float(snr),
        "seed": cfg.get("seed"),
    }
    if None not in (row["n_dips"], row["resolution"], row["ndim"]):
        row["dips_percent"] = dips_percent(int(row["n_dips"]), int(row["resolution"]), int(row["ndim"]),
                                           cfg.get("n_slabs"))
    for key, value in m.items():
        if key not in row and (isinstance(value, (int, float, str)) or value is None):
            row[key] = value
    for key, value in override_values(run.overrides).items():
        row.setdefault(key, value)
    row["overrides"] = " ".join(run.overrides)
    row["error"] = run.error
    return row


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

    Returns one dict per group, sorted by ``by``: the ``by`` keys, ``runs`` (number of ok jobs)
    and ``<metric>_mean``, ``<metric>_std`` for each metric present in the group (non-finite
    values are left out of that metric's statistics; a metric absent from every row of a group
    is absent from the group's dict).
    """
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        if row.get("status") == "ok":
            groups.setdefault(tuple(row.get(k) for k in by), []).append(row)
    out = []
    for key in sorted(groups, key=lambda k: tuple(_sort_key(v) for v in k)):
        members = groups[key]
        entry: dict[str, Any] = dict(zip(by, key))
        entry["runs"] = len(members)
        for name in metrics:
            values = np.array([float(r[name]) for r in members
                               if isinstance(r.get(name), (int, float)) and not isinstance(r.get(name), bool)])
            values = values[np.isfinite(values)]
            if values.size:
                entry[f"{name}_mean"] = float(values.mean())
                entry[f"{name}_std"] = float(values.std(ddof=1)) if values.size > 1 else 0.0
        out.append(entry)
    return out


def label_series(rows: Sequence[dict]) -> list[dict]:
    """Copies of the rows with a ``series`` label for plotting: the solver, and the noise level
    too (``"lsmr @ 30 dB"``, ``"lsmr @ no noise"``) when the ok rows hold more than one."""
    levels = {r.get("snr_db") for r in rows if r.get("status") == "ok"}

    def label(r: dict) -> str:
        if len(levels) < 2:
            return str(r.get("solver"))
        snr = r.get("snr_db")
        return f"{r.get('solver')} @ " + ("no noise" if snr is None else f"{snr:g} dB")

    return [{**r, "series": label(r)} for r in rows]


def problems(runs: Sequence[Run]) -> list[Run]:
    """The failed and unfinished runs."""
    return [r for r in runs if r.status != "ok"]


# --------------------------------------------------------------------------- tables

def write_csv(rows: Sequence[dict], path: str | Path) -> Path:
    """Rows as CSV; columns are the union of the rows' keys in first-seen order (``""`` = missing)."""
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return path


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.3e}"


def format_cell(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, float):
        return _fmt(value)
    return str(value).replace("|", "\\|")


def markdown_table(groups: Sequence[dict], by: Sequence[str] = GROUP_BY,
                   metrics: Sequence[str] = METRICS) -> str:
    """A Markdown table of :func:`aggregate`'s output: one row per group, ``mean ± std`` cells.

    Metrics absent from every group are left out; ``snr_db = none`` means noise-free.
    """
    present = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    header = [LABELS.get(k, k) for k in by] + ["runs"] + [LABELS.get(m, m) for m in present]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for g in groups:
        cells = [format_cell(g.get(k)) for k in by] + [str(g["runs"])]
        cells += [f"{_fmt(g[f'{m}_mean'])} ± {_fmt(g[f'{m}_std'])}" if f"{m}_mean" in g else "" for m in present]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def markdown_problems(runs: Sequence[Run], root: str | Path | None = None) -> str:
    """A Markdown list of failed and unfinished jobs (empty string when there are none)."""
    bad = problems(runs)
    if not bad:
        return ""
    lines = [f"Failed or unfinished jobs ({len(bad)} of {len(runs)}):", ""]
    for row, run in zip(run_rows(bad, root), bad):
        what = run.error or "no metrics.json (unfinished or killed)"
        lines.append(f"- `{row['job']}` ({run.status}): {what}" + (f" [{row['overrides']}]" if row["overrides"] else ""))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- plots

def mean_series(groups: Sequence[dict], line: str, x: str, metric: str) -> dict[Any, tuple[np.ndarray, ...]]:
    """``{line value: (x, mean, std)}`` over the groups that have ``metric`` and a numeric ``x``."""
    out: dict[Any, list] = {}
    for g in groups:
        if f"{metric}_mean" in g and isinstance(g.get(x), (int, float)):
            out.setdefault(g.get(line), []).append((float(g[x]), g[f"{metric}_mean"], g[f"{metric}_std"]))
    series = {}
    for key in sorted(out, key=_sort_key):
        pts = np.array(sorted(out[key]))
        series[key] = (pts[:, 0], pts[:, 1], pts[:, 2])
    return series


def _errorbar_panels(groups: Sequence[dict], x: str, panels: Sequence[str], path: str | Path, *,
                     line: str, xlabel: str, title: str, logx: bool) -> Path:
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), squeeze=False)
    for ax, metric in zip(axes[0], panels):
        ticks: set[float] = set()
        for key, (xs, mean, std) in mean_series(groups, line, x, metric).items():
            ax.errorbar(xs, mean, yerr=std, marker="o", capsize=3, label=format_cell(key))
            ticks.update(float(v) for v in xs)
        ax.set(xlabel=xlabel, ylabel=LABELS.get(metric, metric), title=LABELS.get(metric, metric))
        if logx:
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        if ticks:  # a tick labelled at every measured x (a log axis within one decade has none)
            ax.set_xticks(sorted(ticks), [format_cell(v) for v in sorted(ticks)])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, title=LABELS.get(line, line), title_fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_vs_dips(groups: Sequence[dict], path: str | Path, *, metrics: Sequence[str] = ("iou", "chamfer"),
                 line: str = "solver", x: str = "n_dips") -> Path:
    """IoU and Chamfer vs number of dips, one line per solver, mean ± std (paper Fig. 13a).

    ``groups`` from :func:`aggregate` grouped by at least ``line`` and ``x`` (``x`` may be
    ``dips_percent``). Noisy and noise-free groups are separate points: filter the rows first
    (e.g. noise-free only) for one curve per solver.
    """
    panels = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    if not panels:
        raise ValueError(f"none of the metrics {list(metrics)} is in the aggregated groups")
    xlabel = "% of the dips a square system needs" if x == "dips_percent" else "number of dips"
    return _errorbar_panels(groups, x, panels, path, line=line, xlabel=xlabel, logx=True,
                            title="reconstruction error vs number of dips")


def plot_vs_snr(groups: Sequence[dict], path: str | Path, *,
                metrics: Sequence[str] = ("false_positive", "false_negative"), line: str = "solver") -> Path:
    """False positives and false negatives (fractions of voxels) vs SNR in dB, one line per
    solver (paper Fig. 13b). Noise-free groups (``snr_db`` None) have no place on the axis and
    are left out. Falls back to ``1 - IoU`` when the groups hold neither FP nor FN."""
    panels = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    if not panels:
        groups = [{**g, "error_1_minus_iou_mean": 1 - g["iou_mean"], "error_1_minus_iou_std": g["iou_std"]}
                  for g in groups if "iou_mean" in g]
        panels = ["error_1_minus_iou"]
    if not any(isinstance(g.get("snr_db"), (int, float)) for g in groups):
        raise ValueError("no group has a finite snr_db: run a noise sweep (experiment=snr_sweep)")
    return _errorbar_panels(groups, "snr_db", panels, path, line=line, xlabel="SNR (dB)", logx=False,
                            title="reconstruction error vs noise")


def render_volume(binary: np.ndarray) -> np.ndarray:
    """A picture of a boolean volume: the image itself in 2D (``[y, x]``, y up); in 3D a
    depth-shaded view from the front (looking along +y, x right, z up) of the first occupied
    voxel along each line of sight, brighter = nearer. Returns ``(rows, cols)`` floats in
    ``[0, 1]`` (0 = background), row 0 at the top."""
    vol = np.asarray(binary, dtype=bool)
    if vol.ndim == 2:
        return vol[::-1].astype(np.float64)       # y up
    if vol.ndim != 3:
        raise ValueError(f"volume must be 2D or 3D, got shape {vol.shape}")
    view = np.moveaxis(vol, 1, 0)                # [y, z, x]: depth along y
    hit = view.any(axis=0)
    depth = np.argmax(view, axis=0).astype(np.float64) / max(view.shape[0] - 1, 1)
    gz, gx = np.gradient(np.where(hit, depth, 1.0))
    shade = 1.0 / np.sqrt(1.0 + 25.0 * (gz ** 2 + gx ** 2))   # Lambert-like, light along the view
    image = np.where(hit, (0.35 + 0.65 * (1.0 - depth)) * (0.4 + 0.6 * shade), 0.0)
    return image[::-1]                            # z up


_MONTAGE_CMAP = matplotlib.colormaps["bone"].with_extremes(bad="white")


def _row_label(row: dict, row_key: str | Sequence[str]) -> Any:
    keys = [row_key] if isinstance(row_key, str) else list(row_key)
    return row.get(keys[0]) if len(keys) == 1 else " / ".join(format_cell(row.get(k)) for k in keys)


def pick_montage(runs: Sequence[Run], row_key: str | Sequence[str] = "solver",
                 col_key: str = "n_dips") -> dict[tuple, Run]:
    """One ok run per (row, column) cell, preferring noise-free, then the lowest seed.

    ``row_key``: a row column (e.g. ``"solver"``) or several (``("shape", "solver")``, labels
    joined by `` / ``)."""
    cells: dict[tuple, tuple] = {}
    for run, row in zip(runs, run_rows(runs)):
        if run.status != "ok" or not (run.path / "reconstruction.npz").is_file():
            continue
        key = (_row_label(row, row_key), row.get(col_key))
        rank = (row.get("snr_db") is not None, _sort_key(row.get("seed")))
        if key not in cells or rank < cells[key][0]:
            cells[key] = (rank, run)
    return {k: v[1] for k, v in cells.items()}


def varying(rows: Sequence[dict], keys: Sequence[str] = ("shape", "solver")) -> list[str]:
    """The ``keys`` that take more than one value over the ok rows (``["solver"]`` if none does)."""
    ok = [r for r in rows if r.get("status") == "ok"]
    return [k for k in keys if len({r.get(k) for r in ok}) > 1] or ["solver"]


def plot_montage(runs: Sequence[Run], path: str | Path, *, row_key: str | Sequence[str] = "solver",
                 col_key: str = "n_dips") -> Path:
    """Reconstructions vs number of dips (paper Figs. 10/11): one row per ``row_key`` value
    (see :func:`pick_montage`), one column per ``col_key`` value, each cell drawn from the
    job's ``reconstruction.npz`` (:func:`render_volume`), titled with its IoU."""
    cells = pick_montage(runs, row_key, col_key)
    if not cells:
        raise ValueError("no finished run with a reconstruction.npz to draw")
    rows = sorted({k[0] for k in cells}, key=_sort_key)
    cols = sorted({k[1] for k in cells}, key=_sort_key)
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.3 * len(cols), 2.5 * len(rows)), squeeze=False)
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            run = cells.get((r, c))
            if run is None:
                ax.set_axis_off()
                continue
            with np.load(run.path / "reconstruction.npz") as data:
                image = render_volume(data["binary"])
            ax.imshow(np.ma.masked_equal(image, 0.0), cmap=_MONTAGE_CMAP, vmin=0, vmax=1, interpolation="nearest")
            iou = run.metrics.get("iou")
            ax.set_title(f"{LABELS.get(col_key, col_key)} {format_cell(c)}" + ("" if iou is None else f"\nIoU {iou:.2f}"),
                         fontsize=8)
            if j == 0:
                ax.set_ylabel(format_cell(r), fontsize=9)
    fig.suptitle(f"reconstructions vs {LABELS.get(col_key, col_key)}")
    return save_figure(fig, path)


# --------------------------------------------------------------------------- sweep jobs

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


def job_summary(metrics: dict, keys: Sequence[str] = ("iou", "chamfer", "false_positive", "false_negative",
                                                       "profile_residual", "volume_ratio", "consistency",
                                                       "seconds")) -> str:
    """``key=value`` pairs of the given metrics that are present, 4 significant digits."""
    return " ".join(f"{k}={metrics[k]:.4g}" if isinstance(metrics[k], float) else f"{k}={metrics[k]}"
                    for k in keys if k in metrics)


class JobLogCallback(Callback):
    """Hydra callback: one log line per finished job, and the failures listed after a sweep.

    Enable with ``hydra/callbacks: job_log`` (``conf/hydra/callbacks/job_log.yaml``). A job whose
    task raised (without :func:`guarded_job`) also gets its ``error.txt`` here.
    """

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
            log.info("%s done [%s]: %s", tag, overrides, job_summary(run.metrics))
        else:
            log.warning("%s %s [%s]: %s", tag, run.status, overrides, run.error or "no metrics.json written")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            runs = collect_runs(sweep_dir)
        except NoRunsError as exc:
            log.warning("sweep finished: %s", exc)
            return
        bad = problems(runs)
        log.info("sweep finished: %d of %d jobs ok in %s", len(runs) - len(bad), len(runs), sweep_dir)
        for line in markdown_problems(runs, sweep_dir).splitlines()[2:]:
            log.warning("%s", line)
        if bad:
            log.warning("compare the finished ones with: python scripts/compare.py %s", sweep_dir)

