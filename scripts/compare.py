"""Compare the jobs of one or more sweeps: CSV, Markdown table, plots and an HTML page.

    python scripts/reconstruct.py -m solver=minnorm,lsmr n_dips=41,123 hydra.sweep.dir=sweeps/a
    python scripts/compare.py sweeps/a                    # writes sweeps/a/compare/
    python scripts/compare.py sweeps/a sweeps/b -o results --x dips_percent --html

Writes into the output directory: ``runs.csv`` (one row per job, failed and unfinished ones
included), ``summary.csv`` and ``summary.md`` (mean ± std per solver x n_dips x snr_db, or ``--by``; a warning and a
note under the table name any other config option, seeds aside, that differs within a row, such as
``resolution``, with the ``--by`` that splits it; runs whose reconstruction is empty are counted in an ``empty``
column, their Chamfer and Hausdorff, a stand-in of one truth diagonal, left out of the means; then the
failed/unfinished jobs), ``vs_dips.png`` (IoU and Chamfer vs dips, paper Fig. 13a),
``vs_snr.png`` (false positives / negatives vs SNR, Fig. 13b; only when a sweep has noise
levels), ``montage.png`` (reconstructions vs dips, Figs. 10/11) and with ``--html``
``report.html`` (plus each job's own ``report.html``). Runs without a ground truth (recorded
sources) have no IoU or Chamfer: they are compared on the profile residual, the reconstructed /
measured volume ratio and the time (``vs_dips.png`` shows the first two). Exit status 2 when a
directory holds no job, 1 when no job finished or none records a metric to compare.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

from dipnet.experiments import collect, figures, tables
from dipnet.jobs.pipeline import not_rewritten, output_files

#: The files a comparison may write into its output directory (``plotly.min.js`` aside: the pages' shared copy).
COMPARE_OUTPUTS = ("runs.csv", "summary.csv", "summary.md", "vs_dips.png", "vs_snr.png", "montage.png", "report.html")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun (sweep) directories or job directories")
    parser.add_argument("-o", "--out", type=Path, help="output directory (default: <first dir>/compare)")
    parser.add_argument("--by", nargs="+", default=list(collect.GROUP_BY),
                        help="columns to group by (default: solver n_dips snr_db)")
    parser.add_argument("--x", choices=("n_dips", "dips_percent"), default="n_dips",
                        help="horizontal axis of the error-vs-dips plot")
    parser.add_argument("--rows", nargs="+", help="montage rows: run columns such as solver or shape "
                        "(default: those of shape and solver that vary)")
    parser.add_argument("--html", action="store_true", help="also write HTML pages (needs plotly)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            runs = collect.collect_runs(args.dirs)
    except collect.NoRunsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for w in caught:  # e.g. a job given twice: one line each, as the pooled-options warning below
        print(f"warning: {w.message}", file=sys.stderr)
    root = args.dirs[0] if len(args.dirs) == 1 else None
    rows = collect.run_rows(runs, root)
    for flag, columns in (("--by", args.by), ("--rows", args.rows or ())):
        message = collect.unknown_column_error(rows, columns, flag)
        if message:  # a typo (--by solvr): one group of every run, with no word
            print(f"error: {message}", file=sys.stderr)
            return 2
    out = args.out or args.dirs[0] / "compare"
    job = next((run.path for run in runs if out.resolve() == Path(run.path).resolve()), None)
    if job is not None:  # the sweep page overwrote the job's own report.html (--html), the tables mixed with its files
        print(f"error: --out {out} is the folder of the job {job}, whose own files (report.html with --html) the "
              "comparison would overwrite: give another folder (default: <first dir>/compare)", file=sys.stderr)
        return 2
    if out.exists() and not out.is_dir():
        print(f"error: --out {out} is a file: give a folder for the comparison's tables and plots", file=sys.stderr)
        return 2
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a parent that is a file, a missing or read-only mount: one line, not a traceback
        print(f"error: --out {out}: cannot create the folder for the comparison's tables and plots "
              f"({exc.strerror or exc}): give a folder you can write", file=sys.stderr)
        return 2
    if not os.access(out, os.W_OK):  # a read-only folder failed at the first table, after the scan of the runs
        print(f"error: --out {out} is not writable: give a folder you can write for the comparison's tables "
              "and plots", file=sys.stderr)
        return 2
    earlier = output_files(out, COMPARE_OUTPUTS)
    metrics = collect.compared_metrics(rows)
    groups = collect.aggregate(rows, args.by, metrics)
    tables.write_csv(rows, out / "runs.csv")
    problems = tables.markdown_problems(runs, root)
    n_ok = len(runs) - len(collect.problems(runs))
    print(f"{n_ok} of {len(runs)} jobs finished")
    if problems:
        print(problems, end="")
    if not n_ok and len(runs) == 1 and runs[0].error:
        print(f"error: the run in {runs[0].path} failed: {runs[0].error}", file=sys.stderr)
        return 1
    if not n_ok:
        print(f"error: no job in {', '.join(map(str, args.dirs))} finished (no metrics.json); "
              f"see {out / 'runs.csv'}", file=sys.stderr)
        return 1
    if not any(f"{m}_mean" in g for g in groups for m in metrics):
        print(f"error: the finished jobs record none of {', '.join(metrics)} in their metrics.json: "
              f"nothing to compare; see {out / 'runs.csv'}", file=sys.stderr)
        return 1
    note = "\n".join(line for line in (collect.truth_note(rows), collect.empty_note(rows)) if line)
    if note:
        print(note)
    tables.write_csv(groups, out / "summary.csv")
    table = tables.markdown_table(groups, args.by, metrics)
    pooled = tables.pooled_note(collect.pooled_options(runs, rows, args.by), args.by, {k for r in rows for k in r})
    (out / "summary.md").write_text(table + ("\n" + pooled[:1].upper() + pooled[1:] if pooled else "")
                                    + "".join(f"\n{line[:1].upper()}{line[1:]}\n" for line in note.splitlines())
                                    + ("\n" + problems if problems else ""))
    print(table, end="")
    if pooled:
        print(f"warning: {pooled}", end="", file=sys.stderr)
    written = [out / "runs.csv", out / "summary.csv", out / "summary.md"]

    try:
        written.append(figures.plot_vs_dips(collect.curve_groups(rows, args.x, metrics),
                                            out / "vs_dips.png", metrics=collect.curve_metrics(metrics),
                                            line="series", x=args.x))
    except ValueError as exc:
        print(f"skipping vs_dips.png: {exc}")
    if any(isinstance(r.get("snr_db"), float) for r in rows if r["status"] == "ok"):
        written.append(figures.plot_vs_snr(collect.curve_groups(rows, "snr_db"), out / "vs_snr.png", line="series"))
    else:
        print("no noise levels in these runs: skipping vs_snr.png (see experiment=snr_sweep)")
    try:
        written.append(figures.plot_montage(runs, out / "montage.png", row_key=args.rows or figures.varying(rows)))
    except ValueError as exc:
        print(f"skipping montage.png: {exc}")
    if args.html:
        from dipnet.experiments import report

        try:
            report.require_plotly()
        except ImportError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        for run in runs:
            if run.status == "ok":
                report.write_run_report(run.path)
        written.append(report.write_sweep_report(runs, out / "report.html", root=root or out, by=args.by,
                                                 images=[out / "montage.png"]))
    print("wrote " + ", ".join(str(p) for p in written))
    stale = not_rewritten(out, earlier)
    if stale:  # e.g. `-o results` given to two comparisons: the first's report.html beside the second's tables
        print(f"warning: {out} holds {len(stale)} file(s) of an earlier comparison that this one did not write: "
              f"{', '.join(stale)}; they are not this comparison's results: delete them, or give each comparison "
              "its own -o", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
