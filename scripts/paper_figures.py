"""The paper's Fig. 11 (reconstructions vs number of dips) and Fig. 13a (error vs % of N^2 dips).

Runs the reconstruction pipeline (:func:`dipnet.jobs.pipeline.run`, the Hydra config of
``scripts/reconstruct.py``) for every bundled mesh x resolution ``N`` x dip budget (``--percent``
of the ``N^2`` dips a square system needs, Fibonacci hemisphere), one job directory each under
``--out`` (a finished job is reused, so an interrupted run continues; each job records its overrides in
``overrides.json``, and a job made with other overrides is refused before anything runs: use one ``--out``
per solver or setting; every job uses the fast
``fourier`` operator, ``eps=1e-3, upsampfac=1.25``, single precision, and by default ``minnorm``
with at most 60 LSMR iterations. The command line's overrides add to these defaults (``threads=1`` keeps them
all); an override of a default's option replaces that default, and another ``solver=`` or ``operator=`` choice
drops the defaults' options of that group (``solver=voxel``: ``solver.iter_lim=60`` is minnorm's), which a
``note:`` line names before the jobs run (:func:`replaced`). An override of what each job sets itself,
``resolution``, ``n_dips``, ``ndim`` or ``shape``, is refused: ``--n``, ``--percent`` and ``--meshes`` set them), then
writes there

* ``fig11_n<N>.png``: per resolution, one row per mesh, one column per budget (depth-shaded
  renders of the binary reconstructions, as the paper's Fig. 11 rows);
* ``fig13a.png``: Chamfer (mean) and Hausdorff (max) surface distance in bounding-box
  diagonals vs % of ``N^2``, averaged over meshes and resolutions (mean +- std), the paper's
  METRO errors at 10 % (0.0125-0.043) drawn as a band;
* ``summary.md`` / ``runs.csv``: the table printed at the end.

Ends with ``RESULT chamfer_<p>=<mean> hausdorff_<p>=<mean> ...`` per budget ``p`` (and ``empty_<p>=<jobs>`` when
jobs of that budget reconstructed nothing: their distances, a stand-in of one truth diagonal, are not in the means).

    python scripts/paper_figures.py                              # 64 and 128^3, 3 meshes, 1/3/10 %, minnorm
    python scripts/paper_figures.py solver=voxel --n 64          # any Hydra override of reconstruct.py
    python scripts/paper_figures.py --n 240 --percent 1 3 5 10 --meshes bunny hand   # the paper's size
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from hydra import compose, initialize_config_module  # noqa: E402

from dipnet.experiments import collect, figures, tables  # noqa: E402
from dipnet.jobs import sweep_jobs  # noqa: E402
from dipnet.preprocessing.datasets import check_mesh_names  # noqa: E402
from dipnet.jobs.cli import user_errors  # noqa: E402
from dipnet.jobs.options import check_config  # noqa: E402
from dipnet.jobs.pipeline import run  # noqa: E402

PAPER_METRO_10 = (0.0125, 0.0433)  # paper Table 1: METRO error / bbox diagonal at 10 % of N^2 (240^3)
JOB_DEFAULTS = ["output.figures=false", "output.uncertainty=false", "output.resolvability=false",
                "output.progress=false", "output.mesh_formats=[]", "output.truth_supersample=2", "shape=mesh",
                "shape.radius=45",  # mm: the bundled meshes come in mixed units; the grid follows them
                "operator=fourier", "operator.eps=1e-3", "operator.upsampfac=1.25", "operator.single=true"]
SOLVER_DEFAULTS = ["solver=minnorm", "solver.iter_lim=60"]  # LSMR at these sizes, as in bench_scale
#: The config groups whose defaults' options belong to the default's choice: another choice of the group on the
#: command line drops them, as an override of one of them replaces it (:func:`replaced`).
CHOICE_GROUPS = ("operator", "solver")
OVERRIDES_FILE = "overrides.json"  # a job's overrides, beside its metrics.json
#: The options each job's overrides set from the command line's own flags (:func:`job_overrides`), and the flag:
#: an override of one would run every job at one value under names, N and % that say another.
PER_JOB_OPTIONS = {"resolution": "--n", "n_dips": "--percent", "ndim": None, "shape": "--meshes",
                   "shape.path": "--meshes"}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("overrides", nargs="*", default=[],
                   help=f"Hydra overrides for every job, added to the defaults {' '.join(SOLVER_DEFAULTS)} "
                        "(another solver= or operator= drops that group's defaults; e.g. solver=voxel, threads=1)")
    p.add_argument("--meshes", nargs="+", default=["bunny", "hand", "spot"], help="bundled mesh names")
    p.add_argument("--n", type=int, nargs="+", default=[64, 128], help="grid resolutions N")
    p.add_argument("--percent", type=float, nargs="+", default=[1.0, 3.0, 10.0], help="dips in %% of N^2")
    p.add_argument("--out", type=Path, default=Path("sweeps/paper_figures"), help="job directories and figures")
    args = p.parse_args(argv)
    if not all(math.isfinite(x) and x > 0 for x in args.percent) or any(n < 8 for n in args.n):
        p.error(f"--percent must be finite, positive shares of N^2 and --n at least 8, got --percent "
                f"{' '.join(f'{x:g}' for x in args.percent)} and --n {' '.join(map(str, args.n))}")
    for n in args.n:
        for percent in args.percent:
            message = budget_error(n, percent)
            if message:
                p.error(message)
    return args


#: How far above the asked share the rounded-up dip count may lie (relative) and still be tabled as that share.
BUDGET_TOLERANCE = 0.05


def dip_budget(n: int, percent: float) -> int:
    """The dips of a job at ``N^3`` asked ``percent`` % of ``N^2``: ``ceil(percent/100 N^2)``."""
    return math.ceil(percent / 100 * n * n)


def budget_error(n: int, percent: float) -> str | None:
    """A message when ``percent`` % of ``N^2`` is so few dips that rounding up to a whole dip moves the share by more
    than :data:`BUDGET_TOLERANCE` (the table, ``fig13a.png`` and ``RESULT`` name the asked share), else ``None``."""
    asked = percent / 100 * n * n
    n_dips = dip_budget(n, percent)
    if n_dips <= asked * (1 + BUDGET_TOLERANCE):
        return None
    return (f"--percent {percent:g} at --n {n} asks {asked:.3g} dips: the job would run {n_dips} "
            f"({100 * n_dips / n / n:.3g} % of N^2), tabled as {percent:g} %; give a larger --n or --percent "
            f"({100 * round(1 / BUDGET_TOLERANCE) / n / n:.3g} % or more at --n {n} rounds within "
            f"{100 * BUDGET_TOLERANCE:g} %)")


def _key(override: str) -> str:
    """The option an override sets or deletes (``+``, ``++`` and ``~`` prefixes dropped)."""
    return override.lstrip("+~").partition("=")[0]


def replaced(default: str, overrides: list[str]) -> bool:
    """Whether the command line's ``overrides`` replace ``default``, one of the operator's or solver's defaults
    (:data:`CHOICE_GROUPS`): an override of the same option (``solver.iter_lim=300``), or another choice of its
    group (``solver=voxel`` replaces ``solver=minnorm`` and ``solver.iter_lim=60``, an option voxel has not). The
    other defaults stay, an override of them coming after them."""
    group = _key(default).split(".")[0]
    if group not in CHOICE_GROUPS:
        return False
    choice = next((d.partition("=")[2] for d in [*JOB_DEFAULTS, *SOLVER_DEFAULTS] if _key(d) == group), None)
    return any((_key(o) == _key(default) and o != default) or (_key(o) == group and o.partition("=")[2] != choice)
               for o in overrides)


def kept(defaults: list[str], overrides: list[str]) -> list[str]:
    """``defaults`` less those the command line's ``overrides`` replace (:func:`replaced`) or repeat."""
    return [d for d in defaults if not replaced(d, overrides) and d not in overrides]


def replaced_note(overrides: list[str]) -> str | None:
    """A ``note:`` line naming the defaults the command line's ``overrides`` replace and the overrides that do,
    ``None`` when they replace none (before, any override dropped ``solver=minnorm solver.iter_lim=60`` without
    a word)."""
    defaults = [*JOB_DEFAULTS, *SOLVER_DEFAULTS]
    dropped = [d for d in defaults if replaced(d, overrides)]
    if not dropped:
        return None
    by = [o for o in overrides if any(_key(o) in (_key(d), _key(d).split(".")[0]) for d in dropped)]
    still = [d for d in defaults if _key(d).split(".")[0] in CHOICE_GROUPS and d not in dropped]
    return (f"note: {' '.join(by)} replace{'s' * (len(by) == 1)} the default{'s' * (len(dropped) > 1)} "
            f"{' '.join(dropped)}" + (f"; {' '.join(still)} still appl{'ies' if len(still) == 1 else 'y'}"
                                      if still else ""))


def job_overrides(mesh: str, n: int, percent: float, extra: list[str]) -> list[str]:
    """The pipeline overrides of one job: :func:`dip_budget` dips of ``mesh`` at ``N^3``, the defaults that the
    command line's ``extra`` does not replace (:func:`kept`), then ``extra``."""
    n_dips = dip_budget(n, percent)
    return [*kept(JOB_DEFAULTS, extra), f"shape.path=${{dipnet_data:meshes/{mesh}.ply}}", f"resolution={n}",
            f"n_dips={n_dips}", "ndim=3", *kept(SOLVER_DEFAULTS, extra), *extra]


def check_settings(args) -> None:
    """Raise ``ValueError``, ``FileNotFoundError`` (or Hydra's error) for a setting the jobs cannot run with, before
    any job: a name of ``--meshes`` that is not a bundled mesh, an override of an option each job sets itself
    (:data:`PER_JOB_OPTIONS`), an unknown config choice (``solver=foo``) or an option out of range
    (:func:`~dipnet.jobs.options.check_config` of every job's config)."""
    check_mesh_names(args.meshes)
    for item in args.overrides:
        key = item.lstrip("+~").partition("=")[0]
        if key in PER_JOB_OPTIONS:
            flag = PER_JOB_OPTIONS[key]
            instead = f"give {flag} instead" if flag else "the figures are of 3D jobs"
            raise ValueError(f"override {item}: paper_figures.py sets {key} for each job from --meshes, --n and "
                             f"--percent (the job names and the table's N and % of N^2 would not be the jobs' "
                             f"own): {instead}")
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        for *_, overrides in jobs(args):
            check_config(compose(config_name="config", overrides=overrides))


def jobs(args) -> list[tuple[str, int, float, Path, list[str]]]:
    """``(mesh, N, percent, job directory, overrides)`` of every job the arguments ask for."""
    return [(mesh, n, percent, args.out / job_name(mesh, n, percent), job_overrides(mesh, n, percent, args.overrides))
            for n in args.n for mesh in args.meshes for percent in args.percent]


def other_settings(args) -> list[str]:
    """The finished jobs under ``--out`` made with other overrides than these arguments give them (or recording
    none), one line each: reusing them would table another setting's numbers as this one's."""
    found = []
    for _, _, _, job, overrides in jobs(args):
        if not (job / collect.METRICS_FILE).is_file():
            continue
        try:
            recorded = json.loads((job / OVERRIDES_FILE).read_text())
        except (OSError, ValueError):
            recorded = None
        if recorded != overrides:
            differ = "records no overrides" if not isinstance(recorded, list) else \
                "was made with " + " ".join(sorted(set(recorded) - set(overrides))) + \
                " (now " + " ".join(sorted(set(overrides) - set(recorded))) + ")"
            found.append(f"{job.name} {differ}")
    return found


def run_jobs(args) -> None:
    """Run every missing job (a failed one writes ``error.txt`` and the others go on)."""
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        for mesh, n, percent, job, overrides in jobs(args):
            if (job / collect.METRICS_FILE).is_file():
                continue
            cfg = compose(config_name="config", overrides=overrides)
            print(f"{mesh} {n}^3 {percent:g}% ({cfg.n_dips} dips) -> {job}", flush=True)
            job.mkdir(parents=True, exist_ok=True)
            (job / OVERRIDES_FILE).write_text(json.dumps(overrides) + "\n")
            sweep_jobs.guarded_job(lambda cfg=cfg, job=job: run(cfg, job), job)


def job_name(mesh: str, n: int, percent: float) -> str:
    """The job directory's name; :func:`nominal_rows` reads the budget back from it."""
    return f"{mesh}_n{n}_p{percent:g}"


def nominal_rows(args) -> tuple[list[dict], list]:
    """The runs of the jobs these arguments ask for and their rows (:func:`~dipnet.experiments.collect.run_row`)
    with ``percent``: the requested budget (41 dips at 64^3 and 164 at 128^3 are both 1 %). Other jobs under
    ``--out`` (an earlier call's other meshes, resolutions or budgets) are left out: they are not this call's."""
    runs = collect.collect_runs(job for *_, job, _ in jobs(args) if job.is_dir() and collect.find_job_dirs(job))
    rows = collect.run_rows(runs, args.out)
    for row in rows:
        row["percent"] = float(Path(row["job"]).name.rsplit("_p", 1)[1])
    return rows, runs


def plot_fig13a(groups: list[dict], path: Path) -> Path:
    """Chamfer and Hausdorff (mean +- std over meshes and resolutions) vs % of N^2, with the paper's band."""
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    x = [g["percent"] for g in groups]
    for metric, marker in (("chamfer", "o"), ("hausdorff", "s")):
        ax.errorbar(x, [g.get(f"{metric}_mean", math.nan) for g in groups],
                    yerr=[g.get(f"{metric}_std", math.nan) for g in groups],
                    marker=marker, capsize=3, label=f"dipnet {collect.LABELS[metric]} (mean over objects, N)")
    ax.fill_between([9.0, 11.0], *PAPER_METRO_10, color="tab:red", alpha=0.25, label="paper METRO at 10% (Table 1)")
    ax.set(xscale="log", yscale="log", xlabel="% of the N^2 dips a square system needs",
           ylabel="surface distance / bbox diagonal", title="error vs number of dips (paper Fig. 13a)")
    ax.set_xticks(x, [f"{v:g}" for v in x])
    ax.minorticks_off()
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _cell(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec``, or ``-`` where a metric is undefined (``null`` in ``metrics.json``:
    an empty truth has no IoU, an empty result no Chamfer)."""
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def _distance_cell(row: dict, metric: str) -> str:
    """A run's Chamfer or Hausdorff distance; ``empty`` for a run that reconstructed nothing (its 1.0 is a
    stand-in of one truth diagonal, :data:`~dipnet.experiments.collect.EMPTY_STANDINS`)."""
    return "empty" if collect.is_empty(row) else _cell(row.get(metric), ".4f")


def summary(rows: list[dict], groups: list[dict]) -> str:
    """Markdown: per mesh x N rows, then the mean over them per budget, next to the paper's numbers
    (``-`` for a metric a run leaves undefined; ``empty`` for the distances of a run that reconstructed nothing,
    which the means leave out and the ``jobs`` column counts)."""
    ok = sorted((r for r in rows if r["status"] == "ok"), key=lambda r: (r["shape"], r["resolution"], r["percent"]))
    lines = ["| mesh | N | dips | % of N^2 | IoU | Chamfer | Hausdorff | solve s |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['shape']} | {r['resolution']} | {r['n_dips']} | {r['percent']:g} | {_cell(r.get('iou'), '.3f')} | "
              f"{_distance_cell(r, 'chamfer')} | {_distance_cell(r, 'hausdorff')} | {r['seconds']:.1f} |"
              for r in ok]
    lines += ["", "| % of N^2 | jobs | Chamfer (mean +- std) | Hausdorff (mean +- std) | paper METRO |",
              "|---|---|---|---|---|"]
    for g in groups:
        paper = f"{PAPER_METRO_10[0]}-{PAPER_METRO_10[1]}" if g["percent"] == 10 else ""
        spread = [f"{_cell(g.get(f'{m}_mean'), '.4f')} +- {_cell(g.get(f'{m}_std'), '.4f')}"
                  for m in ("chamfer", "hausdorff")]
        jobs = f"{g['runs']} ({g['empty']} empty, not in the means)" if g.get("empty") else str(g["runs"])
        lines.append(f"| {g['percent']:g} | {jobs} | {spread[0]} | {spread[1]} | {paper} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    with user_errors():  # a bad mesh name or override, an --out that cannot hold the jobs: one line and exit 2,
        check_settings(args)  # before any job
        if args.out.exists() and not args.out.is_dir():
            raise ValueError(f"--out {args.out} is a file: give a folder for the job directories and figures")
        args.out.mkdir(parents=True, exist_ok=True)  # a parent that is a file, a read-only mount: named here
    note = replaced_note(args.overrides)
    if note:  # an override that replaced a default used to do so without a word
        print(note)
    other = other_settings(args)
    if other:
        print(f"error: {args.out} holds finished jobs of another setting ({'; '.join(other[:3])}"
              f"{f'; and {len(other) - 3} more' if len(other) > 3 else ''}): use another --out for this one",
              file=sys.stderr)
        return 2
    run_jobs(args)
    rows, runs = nominal_rows(args)
    failed = tables.markdown_problems(runs, args.out)
    groups = collect.aggregate(rows, ("percent",), metrics=("iou", "chamfer", "hausdorff"))
    if not groups:
        print(f"error: no job under {args.out} finished\n{failed}")
        return 1
    tables.write_csv(rows, args.out / "runs.csv")
    table = summary(rows, groups) + ("\n" + failed if failed else "")
    (args.out / "summary.md").write_text(table)
    print(table, end="")
    plot_fig13a(groups, args.out / "fig13a.png")
    written = [args.out / "fig13a.png"]
    for n in sorted({r["resolution"] for r in rows if r["status"] == "ok"}):  # Fig. 11: one resolution each
        same_n = [run for run, row in zip(runs, rows) if row["resolution"] == n]
        written.append(figures.plot_montage(same_n, args.out / f"fig11_n{n}.png", row_key="shape",
                                            col_key="n_dips"))
    print("figures: " + ", ".join(map(str, written)))
    print("RESULT " + " ".join(f"{m}_{g['percent']:g}={g.get(f'{m}_mean', math.nan):.4f}"
                               for g in groups for m in ("chamfer", "hausdorff"))
          + "".join(f" empty_{g['percent']:g}={g['empty']}" for g in groups if g.get("empty")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
