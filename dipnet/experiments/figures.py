"""Figures of a sweep: metrics against dips or SNR, and montages of reconstructions."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.colors
import matplotlib.ticker
from matplotlib.patches import Patch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from dipnet.experiments.collect import LABELS, Run, _sort_key, override_values, run_rows
from dipnet.experiments.tables import format_cell
from dipnet.outputs.plots import save_figure  # noqa: E402


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
    """IoU and Chamfer (or other ``metrics``) vs number of dips, one line per solver, mean ± std
    (paper Fig. 13a).

    ``groups`` from :func:`aggregate` grouped by at least ``line`` and ``x`` (``x`` may be
    ``dips_percent``). Noisy and noise-free groups are separate points: filter the rows first
    (e.g. noise-free only) for one curve per solver.
    """
    panels = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    if not panels:
        raise ValueError(f"none of the metrics {list(metrics)} is in the aggregated groups")
    xlabel = "% of the dips a square system needs" if x == "dips_percent" else "number of dips"
    return _errorbar_panels(groups, x, panels, path, line=line, xlabel=xlabel, logx=True,
                            title=" and ".join(LABELS.get(m, m) for m in panels) + " vs number of dips")


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


def render_volume(binary: np.ndarray, cut: bool = False) -> np.ndarray:
    """A picture of a boolean volume: the image itself in 2D (``[y, x]``, y up); in 3D a
    depth-shaded view from the front (looking along +y, x right, z up) of the first occupied
    voxel along each line of sight, brighter = nearer. ``cut``: the front half (``y`` below the
    middle voxel plane) removed first, so the view shows the mid-plane section and inner
    cavities behind it. Returns ``(rows, cols)`` floats in ``[0, 1]`` (0 = background), row 0
    at the top."""
    vol = np.asarray(binary, dtype=bool)
    if vol.ndim == 2:
        return vol[::-1].astype(np.float64)       # y up
    if vol.ndim != 3:
        raise ValueError(f"volume must be 2D or 3D, got shape {vol.shape}")
    view = np.moveaxis(vol, 1, 0)                # [y, z, x]: depth along y
    if cut:
        view = view[vol.shape[1] // 2:]
    hit = view.any(axis=0)
    depth = np.argmax(view, axis=0).astype(np.float64) / max(view.shape[0] - 1, 1)
    gz, gx = np.gradient(np.where(hit, depth, 1.0))
    shade = 1.0 / np.sqrt(1.0 + 25.0 * (gz ** 2 + gx ** 2))   # Lambert-like, light along the view
    image = np.where(hit, (0.35 + 0.65 * (1.0 - depth)) * (0.4 + 0.6 * shade), 0.0)
    return image[::-1]                            # z up


def mid_section(binary: np.ndarray) -> np.ndarray:
    """The plane a cut :func:`render_volume` shows in front, as drawn: the mid-``y`` plane
    ``[z, x]`` of a 3D volume (z up), the image itself in 2D (y up); boolean."""
    vol = np.asarray(binary, dtype=bool)
    return (vol[:, vol.shape[1] // 2, :] if vol.ndim == 3 else vol)[::-1]


def differing_overrides(runs: Sequence[Run]) -> dict[Path, str]:
    """For each run, its overrides whose value is not the same in every run
    (``"solver=voxel n_dips=41"``; ``"(same overrides)"`` if none differs)."""
    values = [override_values(r.overrides) for r in runs]
    keys = sorted({k for v in values for k in v})
    differ = [k for k in keys if len({format_cell(v.get(k)) for v in values}) > 1]
    return {r.path: " ".join(f"{k}={format_cell(v.get(k))}" for k in differ) or "(same overrides)"
            for r, v in zip(runs, values)}


_MONTAGE_CMAP = matplotlib.colormaps["Greys"].with_extremes(bad="white")  # nearer = darker, the cut face darkest
_DIFF_COLORS = ("#d62728", "#1f77b4")
_DIFF_CMAP = matplotlib.colors.ListedColormap(_DIFF_COLORS).with_extremes(bad=(0, 0, 0, 0))


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
    job's ``reconstruction.npz`` cut open at its middle ``y`` plane (:func:`render_volume`, so
    inner cavities show) and titled with the overrides that differ between the cells
    (:func:`differing_overrides`) and its IoU.

    What differs shows even where the shapes look alike: the cells are zoomed to the
    reconstructions, the one with the best IoU (else the first) is the reference, and every
    other cell marks the voxels of its cut plane that the reference has and it lacks
    (red) or that it has and the reference lacks (blue), with the number of differing voxels
    in the whole volume.
    """
    cells = pick_montage(runs, row_key, col_key)
    if not cells:
        raise ValueError("no finished run with a reconstruction.npz to draw")
    rows = sorted({k[0] for k in cells}, key=_sort_key)
    cols = sorted({k[1] for k in cells}, key=_sort_key)
    order = [cells[(r, c)] for r in rows for c in cols if (r, c) in cells]
    labels = differing_overrides(order)
    volumes = {}
    for run in order:
        with np.load(run.path / "reconstruction.npz") as data:
            volumes[run.path] = np.asarray(data["binary"], dtype=bool)
    reference = max(order, key=lambda run: run.metrics.get("iou") or -1.0)  # the first of the best (null: none)
    ref = volumes[reference.path]
    images = {p: render_volume(v, cut=True) for p, v in volumes.items()}
    # one zoom per picture size: a sweep over resolution (or 2D beside 3D) draws pictures of several sizes
    boxes = {size: _box(np.any([im > 0 for im in images.values() if im.shape == size], axis=0))
             for size in {im.shape for im in images.values()}}
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.8 * len(cols), 3.0 * len(rows) + 0.8),
                             squeeze=False, layout="constrained")
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            run = cells.get((r, c))
            if run is None:
                ax.set_axis_off()
                continue
            vol = volumes[run.path]
            ax.imshow(np.ma.masked_equal(images[run.path], 0.0), cmap=_MONTAGE_CMAP, vmin=-0.5, vmax=1.1,
                      interpolation="nearest")
            (r0, c0), (r1, c1) = boxes[images[run.path].shape]
            ax.set(xlim=(c0 - 0.5, c1 + 0.5), ylim=(r1 + 0.5, r0 - 0.5))
            iou = run.metrics.get("iou")
            note = "" if iou is None else f"IoU {iou:.3f}"
            if run is reference:
                note += " · reference"
            elif vol.shape == ref.shape:
                lost, extra = mid_section(ref) & ~mid_section(vol), mid_section(vol) & ~mid_section(ref)
                overlay = np.where(lost, 1.0, np.where(extra, 2.0, np.nan))
                ax.imshow(overlay, cmap=_DIFF_CMAP, vmin=1, vmax=2, interpolation="nearest")
                note += f" · {int((vol != ref).sum())} voxels differ"
            ax.set_title(f"{_wrap(labels[run.path])}\n{note.strip(' ·')}", fontsize=7)
            if j == 0:
                ax.set_ylabel(format_cell(r), fontsize=9)
    fig.legend(handles=[Patch(color=_DIFF_COLORS[0], label="in the reference, not here"),
                        Patch(color=_DIFF_COLORS[1], label="here, not in the reference")],
               loc="lower center", ncol=2, fontsize=8, title="mid-plane section vs the reference (best IoU)",
               title_fontsize=8, bbox_to_anchor=(0.5, -0.01))
    fig.get_layout_engine().set(rect=(0, 0.06, 1, 0.94))
    fig.suptitle(f"reconstructions vs {LABELS.get(col_key, col_key)}, cut open at the middle y plane")
    return save_figure(fig, path)


def _box(mask: np.ndarray, margin: int = 1) -> tuple[tuple[int, int], tuple[int, int]]:
    """``((row0, col0), (row1, col1))``: the true pixels' bounding box plus ``margin``, inside the image."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return (0, 0), (mask.shape[0] - 1, mask.shape[1] - 1)
    return ((max(rows[0] - margin, 0), max(cols[0] - margin, 0)),
            (min(rows[-1] + margin, mask.shape[0] - 1), min(cols[-1] + margin, mask.shape[1] - 1)))


def _wrap(text: str, width: int = 34) -> str:
    """``text`` broken at spaces into lines of about ``width`` characters."""
    lines: list[str] = []
    for word in text.split():
        if lines and len(lines[-1]) + 1 + len(word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return "\n".join(lines)
