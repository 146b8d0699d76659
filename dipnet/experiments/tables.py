"""Tables of a sweep: CSV, Markdown summaries and the list of failed or unfinished jobs."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dipnet.experiments.collect import EMPTY_STANDINS, GROUP_BY, LABELS, METRICS, Run, problems, run_rows


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

    Metrics absent from every group are left out; ``snr_db = none`` means noise-free; ``consistent``: how many
    of a row's runs passed their consistency check (when the runs record it); ``failed``: how many of the row's jobs
    failed or did not finish (when any did: not in the means); ``empty``: how many reconstructed
    nothing (when any did: their Chamfer and Hausdorff, a stand-in, are not in the means).
    """
    present = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    verdicts = any("consistent" in g for g in groups)
    empties = any("empty" in g for g in groups)
    failures = any("failed" in g for g in groups)
    header = [LABELS.get(k, k) for k in by] + ["runs"] + (["failed"] if failures else []) + \
        (["consistent"] if verdicts else []) + (["empty"] if empties else []) + [LABELS.get(m, m) for m in present]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for g in groups:
        cells = [format_cell(g.get(k)) for k in by] + [str(g["runs"])]
        cells += [str(g.get("failed", 0))] if failures else []
        cells += [f"{g['consistent']} of {g['runs']}" if "consistent" in g else ""] if verdicts else []
        cells += [f"{g.get('empty', 0)} of {g['runs']}"] if empties else []
        cells += [metric_cell(g, m) for m in present]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def metric_cell(group: dict, metric: str) -> str:
    """A group's ``mean ± std`` of ``metric``; ``none (empty)`` for a stand-in (:data:`EMPTY_STANDINS`) of a group
    whose every run with that metric is empty, ``""`` for a metric the group lacks."""
    if f"{metric}_mean" in group:
        return f"{_fmt(group[f'{metric}_mean'])} ± {_fmt(group[f'{metric}_std'])}"
    return "none (empty)" if metric in EMPTY_STANDINS and group.get("empty") else ""


def _setting(value: Any) -> str:
    """An option's value as set, to 6 significant digits (``0.99999`` is not ``1``, as :func:`format_cell` shows it)."""
    return f"{value:.6g}" if isinstance(value, float) else format_cell(value)


def pooled_note(options: dict[str, list], by: Sequence[str], columns: set[str]) -> str:
    """One line on the summary's rows that pool unlike runs (``""`` when none do).

    ``options``: :func:`~dipnet.experiments.collect.pooled_options`; ``by``: the grouping columns;
    ``columns``: the runs' columns (those options among them can split the rows with ``--by``).
    """
    if not options:
        return ""
    named = "; ".join(f"{k} ({', '.join(_setting(v) for v in values[:4])}{', ...' if len(values) > 4 else ''})"
                      for k, values in options.items())
    note = f"rows of this table pool runs that differ in {named}: their mean ± std mixes those settings"
    split = [k for k in options if k in columns]
    if split:
        note += f"; split them with `--by {' '.join([*by, *split])}`"
    others = [k for k in options if k not in columns]
    if others:
        note += (f"; {', '.join(others)} {'is' if len(others) == 1 else 'are'} no runs.csv column: "
                 "compare those runs separately")
    return note + "\n"


def markdown_problems(runs: Sequence[Run], root: str | Path | None = None) -> str:
    """A Markdown list of failed and unfinished jobs (empty string when there are none)."""
    bad = problems(runs)
    if not bad:
        return ""
    lines = [f"Failed or unfinished jobs ({len(bad)} of {len(runs)}):", ""]
    for row, run in zip(run_rows(bad, root), bad):
        what = run.error or "no metrics.json (unfinished or killed)"
        lines.append(f"- `{row['job']}` ({run.status}): {what}"
                     + (f" [{row['overrides']}]" if row["overrides"] else ""))
    return "\n".join(lines) + "\n"
