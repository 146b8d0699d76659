"""Reconstruction quality of minnorm / voxel / implicit (with and without the learned prior) on
the bundled meshes and on generated test shapes (not a timed test).

For every mesh in ``--meshes-dir`` (scaled to ``--fill`` of the working ball) on an
``--n``^3 grid, every orientation budget (Fibonacci hemisphere; ``--max-tilt-deg T``: the plan of a rig that
tilts 0-T deg, as ``reach=authors_rig`` for 35) and every noise level, the
dips are simulated from the mesh geometry itself (:func:`dipnet.simulator.simulate.simulate_measurement`,
a level sensor with exact readings (``--quantum-mm 0``), noise-free or with white noise at
``--snr`` dB, which the scan states; ``--noise unstated``: the same noise, the scan preprocessed again
without its statement, so the solvers take the noise from the readings) and each solver reconstructs on the ``auto``
operator. Prints one table (IoU, Chamfer / bbox diagonal, Hausdorff / bbox diagonal, wall
time, the TV weight the solver used, the consistency check's verdict), the means per solver / budget / noise,
the headline ratio (best optimiser's mean Chamfer at the smallest budget / minnorm's at the largest, noise-free) and
each mesh's ratio of voxel's Chamfer at the smallest budget to minnorm's at the largest, per noise.

    python scripts/bench_quality.py                                   # the full table
    python scripts/bench_quality.py --quick                           # bunny and torus, 32^3, minnorm and voxel
    python scripts/bench_quality.py --meshes bunny torus --budgets 41 --noise clean --solvers voxel
    python scripts/bench_quality.py --options voxel='{"iterations": 300}'
    python scripts/bench_quality.py --dips voxel=41 minnorm=410                   # the headline pair only
    python scripts/bench_quality.py --headline --generated 50           # the learned prior's targets
    python scripts/bench_quality.py --headline --quick                  # bunny + 2 generated shapes (64^3), 2 processes
    python scripts/bench_quality.py --headline --generated 50 --workers 2  # rows solved in 2 processes, 1 thread each
    python scripts/bench_quality.py --headline --from-json a.json b.json  # summaries of earlier runs' rows

``prior`` is ``solver=voxel_learned`` and ``implicit_prior`` ``solver=implicit_learned``, read from
``conf/solver/`` as a job would: a voxel solve whose result the learned prior's denoiser
(:class:`dipnet.solvers.learned.LearnedPrior`, the shipped 64^3 weights) turns into the anchor of a
refit under the data term. ``--generated K`` adds K generated shapes (:mod:`dipnet.shapes.procedural`) of
seeds ``--generated-first`` .. + K - 1, which must not overlap the seeds the weights were trained
or validated on (refused otherwise). ``--solvers truth`` adds a row with no solve: the truth's own
partial-volume occupancy, what a perfect occupancy estimate on the grid scores (its iso-surface at
0.5 can lose walls thinner than a voxel, which a lower threshold keeps). ``--headline`` runs minnorm
at the largest budget only and the optimisers at the smallest only (what the headline ratios need),
and on the generated shapes only the optimisers. The last line is then
``RESULT prior41_over_minnorm410_median=.. prior41_over_minnorm410_worst=.. snr_worst=.. beats_voxel_generated=..``
(per bundled mesh: prior Chamfer at the smallest budget / minnorm's at the largest, noise-free;
``snr_worst``: the same ratio at ``--snr`` dB, worst mesh; ``beats_voxel_generated``: share of the
generated shapes on which prior's Chamfer is below voxel's at the smallest budget).

Simulated measurements and truths are cached in ``--cache`` (``.npz``), keyed by their parameters, the mesh
file's bytes and the simulation code version (:func:`dipnet.core.code_version.simulation_digest`), so repeated
runs only pay for the solvers and a run after a change to the simulator simulates afresh.
``--workers W`` solves the rows in ``W`` processes (``--threads`` torch threads each, default 1), the
dearest solvers first; the rows are the ones a single process gives, printed as they finish.
"""

from __future__ import annotations

import argparse
import functools
import json
import multiprocessing
import os
import statistics
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch

from dipnet.jobs.configured import check_test_seeds, configured
from dipnet.experiments.bench_options import check_run_options, number_type
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.preprocessing.datasets import MESHES_DIR
from dipnet.core.code_version import simulation_digest
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.consistency import check_consistency
from dipnet.evaluation.metrics import evaluate
from dipnet.experiments.prior_pairs import file_digest, plan_directions
from dipnet.operators import make_operator
from dipnet.preprocessing.preprocess import preprocess
from dipnet.simulator.physics import LevelSensor
from dipnet.shapes import load_mesh
from dipnet.shapes.procedural import generated_shape
from dipnet.simulator.simulate import simulate_measurement
from dipnet.jobs.cli import user_errors
from dipnet.solvers.deep_image_prior import DeepImagePriorSolver
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver
from dipnet.solvers import SOLVERS as SOLVER_CLASSES, check_solver_options

SOLVERS = {"minnorm": MinNormSolver, "voxel": VoxelSolver, "implicit": ImplicitSolver, "dip": DeepImagePriorSolver,
           "prior": configured("voxel_learned"), "implicit_prior": configured("implicit_learned"), "truth": None}
#: Samples per voxel axis of the truth's partial-volume occupancy: the binary truth of every case, and
#: the ``--solvers truth`` row (no solve: what a perfect occupancy estimate on the grid scores).
TRUTH_SUPERSAMPLE = 3
OPTIMISERS = ("voxel", "implicit", "dip", "prior", "implicit_prior")
DEFAULT_MESHES = MESHES_DIR
#: ``--noise`` cases: noise-free; --snr dB that the scan states; the same noise unstated (its statement removed
#: from the raw scan before preprocessing, as a sensor without a noise model gives).
NOISES = ("clean", "snr", "unstated")
#: The ``--meshes`` name that selects no mesh file (with ``--generated``: the generated shapes alone).
NO_MESH = "none"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes-dir", type=Path, default=DEFAULT_MESHES, help="folder of mesh files")
    p.add_argument("--meshes", nargs="*", help="mesh names (file stems) to use; default all; none: no mesh "
                   "(with --generated)")
    p.add_argument("--n", type=int, default=64, help="grid resolution N")
    p.add_argument("--budgets", type=int, nargs="+", default=[41, 123, 410], help="numbers of dips")
    p.add_argument("--solvers", nargs="+", default=["minnorm", "voxel", "implicit"], choices=list(SOLVERS),
                   help="solvers to run (dip, the untrained deep image prior, only when named)")
    p.add_argument("--dips", nargs="+", default=[], metavar="SOLVER=K[,K...]",
                   help="numbers of dips per solver, e.g. voxel=41 minnorm=410 (replaces --budgets and "
                        "--solvers: only the solvers named run, each at its own budgets)")
    p.add_argument("--noise", nargs="+", default=["clean", "snr"], choices=NOISES,
                   help="noise-free and/or level-sensor noise at --snr dB, stated (snr) or not (unstated)")
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR in dB for --noise snr")
    p.add_argument("--quantum-mm", type=number_type("mm", at_least=0), default=0.0,
                   help="level-sensor resolution in mm (0: exact readings, so 'clean' is noise-free; the "
                        "simulator's default 0.01 mm is ~600 mm^3 in its 300 x 200 mm tank)")
    p.add_argument("--fill", type=float, default=0.9, help="mesh radius / working-ball radius")
    p.add_argument("--max-tilt-deg", type=float, default=90.0,
                   help="dip along the nearly uniform plan of a rig that tilts 0 to this many deg (below 90, e.g. 35 "
                        "for reach=authors_rig); 90: the Fibonacci hemisphere")
    p.add_argument("--options", nargs="*", default=[], metavar="SOLVER=JSON",
                   help="constructor options per solver, e.g. voxel='{\"iterations\": 300}'")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads per solve (default: torch's; with --workers above 1: 1)")
    p.add_argument("--workers", type=int, default=None,
                   help="solve in this many processes (default 1; 2 for --headline --quick)")
    p.add_argument("--cache", type=Path, default=Path("outputs/bench_quality_cache"),
                   help="folder caching simulated measurements and truths")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write every row to this JSON file")
    p.add_argument("--from-json", type=Path, nargs="+", metavar="JSON",
                   help="solve nothing: print the summaries (and RESULT line) of rows saved by earlier --json runs")
    p.add_argument("--generated", type=int, default=0, help="number of generated test shapes")
    p.add_argument("--generated-first", type=int, default=0, help="seed of the first generated test shape")
    p.add_argument("--headline", action="store_true",
                   help="minnorm at the largest budget, optimisers at the smallest only; prior RESULT line")
    p.add_argument("--quick", action="store_true",
                   help="bunny and torus at 32^3, 41 and 123 dips, noise-free, minnorm and voxel (a few minutes); "
                        "with --headline: bunny and 2 generated shapes at 64^3, 41 / 410 dips, minnorm, voxel, prior")
    args = p.parse_args(argv)
    if args.quick and args.headline:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), meshes=["bunny"], n=64, budgets=[41, 410], noise=["clean"],
                    solvers=["minnorm", "voxel", "prior"], generated=2, workers=2)
    elif args.quick:
        apply_quick(args, given_options(p, argv), meshes=["bunny", "torus"], n=32, budgets=[41, 123],
                    noise=["clean"], solvers=["minnorm", "voxel"])
    args.workers = 1 if args.workers is None else args.workers
    if args.workers < 1:
        raise ValueError(f"--workers must be 1 or more, got {args.workers}")
    if not 0 < args.max_tilt_deg <= 90:
        raise ValueError(f"--max-tilt-deg must be in (0, 90], got {args.max_tilt_deg:g}")
    check_run_options(args)  # --fill among them: beyond the working ball the profiles lose volume past the grid's slabs
    if not args.from_json and not args.meshes_dir.is_dir():  # was "no meshes found in ... (names None)"
        raise ValueError(f"--meshes-dir {args.meshes_dir}: " + ("a file, not a folder of mesh files"
                         if args.meshes_dir.exists() else "no such folder"))
    if min(args.budgets) < 1:
        raise ValueError(f"--budgets must be positive numbers of dips, got {' '.join(map(str, args.budgets))}")
    if args.dips:  # each solver at its own budgets, with --headline too (whose ratios take the smallest and largest)
        args.plan = solver_budgets(args.dips)
        args.budgets = sorted({k for ks in args.plan.values() for k in ks})
    elif args.headline:  # minnorm at the largest budget, the optimisers at the smallest
        args.plan = {name: [max(args.budgets) if name == "minnorm" else min(args.budgets)] for name in args.solvers}
    else:
        args.plan = {name: list(args.budgets) for name in args.solvers}
    return args


def solver_budgets(specs: list[str]) -> dict[str, list[int]]:
    """``{solver: [numbers of dips]}`` from ``--dips`` entries ``SOLVER=K[,K...]``."""
    out: dict[str, list[int]] = {}
    for spec in specs:
        name, _, text = spec.partition("=")
        try:
            budgets = [int(k) for k in text.split(",")]
        except ValueError:
            budgets = []
        if name not in SOLVERS or not budgets or min(budgets) < 1:
            raise ValueError(f"--dips expects SOLVER=K[,K...] with SOLVER in {list(SOLVERS)}, got {spec!r}")
        out.setdefault(name, []).extend(budgets)
    return out


def solver_options(specs: list[str]) -> dict[str, dict]:
    out = {}
    for spec in specs:
        name, _, text = spec.partition("=")
        if name not in SOLVERS or not text:
            raise ValueError(f"--options expects SOLVER=JSON with SOLVER in {list(SOLVERS)}, got {spec!r}")
        try:
            out[name] = json.loads(text)
        except ValueError as exc:
            out[name] = f"not JSON ({exc})"
        if not isinstance(out[name], dict):
            raise ValueError(f"--options {spec}: the options must be a JSON object of the solver's options, e.g. "
                             f"voxel='{{\"iterations\": 300}}' (got {out[name]})")
        if name == "truth" and out[name]:
            raise ValueError(f"--options {spec}: the truth row solves nothing and takes no options")
        if name in SOLVER_CLASSES:  # was a TypeError traceback at its first solve, after the cases before it
            try:
                check_solver_options(name, out[name])
            except TypeError as exc:
                raise ValueError(f"--options {spec}: {exc}") from None
    return out


def case_data(args, mesh_path: Path, grid: Grid, k: int, noise: str):
    """``(measurement, truth occupancy bool, shape)`` for one mesh / budget / noise, cached under the file's name
    and the digest of its bytes (another file of the same name, or the file edited, is simulated afresh)."""
    return cached_case(args, f"{mesh_path.stem}-{mesh_digest(mesh_path)}",
                       lambda: mesh_shape(mesh_path, args.fill * grid.radius), grid, k, noise)


@functools.cache
def mesh_digest(path: Path) -> str:
    """The sha256 of the mesh file's bytes, 12 hex characters (read once per process)."""
    return file_digest(path)


def generated_case_data(args, seed: int, grid: Grid, k: int, noise: str):
    """As :func:`case_data` for the generated shape of ``seed`` (farthest point at ``--fill`` of the ball)."""
    return cached_case(args, f"generated{seed}", lambda: procedural_shape(seed, args.fill * grid.radius), grid, k,
                       noise)


@functools.cache
def mesh_shape(path: Path, radius: float):
    """The mesh file scaled to ``radius`` (mm), made once per process: the rows of one case share it."""
    return load_mesh(path, radius=radius)


@functools.cache
def procedural_shape(seed: int, radius: float):
    """The generated shape of ``seed`` at ``radius`` (mm), made once per process (about 2 s each)."""
    return generated_shape(seed, radius=radius)


def cached_case(args, name: str, make_shape, grid: Grid, k: int, noise: str):
    """``(measurement, truth occupancy bool, shape)`` of the shape ``make_shape()`` called ``name``."""
    shape = make_shape()
    code = simulation_digest()  # a rerun after a change to the simulator simulates afresh
    reach = "" if args.max_tilt_deg >= 90 else f"_t{args.max_tilt_deg:g}"  # the hemisphere keeps its cached cases
    tag = (f"{name}_n{grid.n}_k{k}_{noise}{'' if noise == 'clean' else args.snr}_q{args.quantum_mm}"
           f"_f{args.fill}{reach}_s{args.seed}_code{code}")
    meas_file = args.cache / f"{tag}.npz"
    truth_file = args.cache / f"{name}_n{grid.n}_f{args.fill}_code{code}_truth.npy"
    args.cache.mkdir(parents=True, exist_ok=True)
    if meas_file.is_file():
        measurement = DipMeasurement.load(meas_file)
    else:
        sensor = LevelSensor(snr_db=None if noise == "clean" else args.snr, quantum_mm=args.quantum_mm, seed=args.seed)
        raw, measurement = simulate_measurement(shape, plan_directions(k, args.max_tilt_deg), grid=grid, sensor=sensor,
                                                seed=args.seed, progress=False)
        if noise == "unstated":
            measurement = preprocess(raw.without_stated_noise(), grid=grid, t_start="metadata")
        write_whole(meas_file, measurement.save)
    if truth_file.is_file():
        truth = np.load(truth_file)
    else:
        truth = shape.occupancy(grid, supersample=TRUTH_SUPERSAMPLE).numpy() >= 0.5
        write_whole(truth_file, lambda path: np.save(path, truth))
    return measurement, truth, shape


def write_whole(path: Path, write: Callable[[Path], object]) -> None:
    """``write(temporary file)`` then rename it to ``path``: a worker that finds ``path`` reads it whole (two
    workers that make one case both write the same file)."""
    part = path.with_name(f"{path.stem}.{os.getpid()}.part{path.suffix}")
    write(part)
    os.replace(part, path)


#: The mesh files of ``--meshes-dir``.
MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off")


#: Solvers in order of cost, the dearest first: with ``--workers`` their rows start first, so the workers end together.
COST_ORDER = ("implicit_prior", "prior", "implicit", "dip", "voxel", "minnorm", "truth")


def solve_row(args, grid: Grid, options: dict, task: tuple) -> dict:
    """One row of the table: ``task = (label, kind, source, k, noise, solver)`` solved and scored (``source``: a
    mesh path, or a generated shape's seed)."""
    label, kind, source, k, noise, name = task
    if kind == "mesh":
        measurement, truth, shape = case_data(args, source, grid, k, noise)
    else:
        measurement, truth, shape = generated_case_data(args, source, grid, k, noise)
    t0 = time.perf_counter()
    if name == "truth":
        recon = Reconstruction(shape.occupancy(grid, supersample=TRUTH_SUPERSAMPLE).float(), grid)
    else:
        operator = make_operator(grid, measurement.directions, grid.n)
        recon = SOLVERS[name](progress=False, **options.get(name, {})).solve(measurement, operator)
    seconds = time.perf_counter() - t0
    scores = evaluate(recon, truth, grid, truth_mesh=shape.mesh)
    rule, refit = recon.info.get("weight_rule") or {}, recon.info.get("surface_refit") or {}
    verdict = None if name == "truth" else check_consistency(measurement, operator, recon, warn=False).verdict
    return {"mesh": label, "set": kind, "dips": k, "noise": noise, "solver": name, "seconds": seconds,
            **{key: scores[key] for key in ("iou", "chamfer", "hausdorff", "volume_error")},
            "tv_weight": (recon.info.get("prior_weights") or {}).get("tv"),
            "weight_rule": rule.get("rule"), "residual_reached": rule.get("residual_reached"),
            "target_residual": rule.get("target_residual"), "verdict": verdict,
            "surface_refit": refit.get("applied"), "surface_folded": refit.get("folded_faces", 0)}


def solved_rows(args, grid: Grid, options: dict, tasks: list[tuple]) -> Iterator[dict]:
    """The rows of ``tasks``, in this process or, with ``--workers`` above 1, in that many processes of
    ``--threads`` (default 1) torch threads each, dearest solvers first; rows come as they finish."""
    if args.workers <= 1:
        for task in tasks:
            yield solve_row(args, grid, options, task)
        return
    dearest_first = sorted(tasks, key=lambda task: COST_ORDER.index(task[-1]))
    with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=torch.set_num_threads, initargs=(args.threads or 1,)) as pool:
        futures = [pool.submit(solve_row, args, grid, options, task) for task in dearest_first]
        for future in as_completed(futures):
            yield future.result()


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option or file: one line ``error: ...`` and exit 2."""
    with user_errors():
        return run(argv)


#: What every row of ``--json`` holds that the summaries read.
ROW_KEYS = ("mesh", "set", "dips", "noise", "solver", "seconds", "iou", "chamfer", "hausdorff")


def read_rows(paths: list[Path]) -> list[dict]:
    """The rows of earlier ``--json`` runs (``--from-json``), in order.

    Raises:
        ValueError: a file that is not JSON, or not a list of rows (objects holding :data:`ROW_KEYS`), or a case
            (mesh, dips, noise, solver) in two rows: a file given twice, or runs of another ``--n``, ``--snr`` or
            ``--fill`` (which the rows do not record), whose means would pool both.
        OSError: a file that cannot be read.
    """
    rows = []
    seen: dict[tuple, Path] = {}
    for path in paths:
        try:
            data = json.loads(path.read_text())
        except ValueError as exc:
            raise ValueError(f"--from-json {path}: not JSON ({exc})") from None
        if not isinstance(data, list):
            problem = f"it holds a JSON {type(data).__name__}"
        else:
            bad = next((i for i, row in enumerate(data) if not isinstance(row, dict) or not set(ROW_KEYS) <= set(row)),
                       None)
            problem = None if bad is None else f"its item {bad} is not"
        if problem:
            raise ValueError(f"--from-json {path}: not the rows of a bench_quality.py --json run (a list of objects "
                             f"holding {', '.join(ROW_KEYS)}; {problem})")
        for row in data:
            case = tuple(row[key] for key in ("mesh", "set", "dips", "noise", "solver"))
            if case in seen:
                raise ValueError(f"--from-json: {row['solver']} on {row['mesh']} at {row['dips']} dips "
                                 f"({row['noise']}) "
                                 f"is in {seen[case]} and in {path}: a file given twice, or runs of another --n, --snr "
                                 "or --fill, whose rows would be averaged as one case; give each case once")
            seen[case] = path
        rows += data
    return rows


def run(argv=None) -> list[dict]:
    """:func:`main`'s work (its errors raised)."""
    args = parse_args(argv)
    if args.from_json:
        rows = read_rows(args.from_json)
        print_all(rows, args)
        return rows
    if args.threads:
        torch.set_num_threads(args.threads)
    options = solver_options(args.options)
    paths = sorted(p for p in args.meshes_dir.glob("*") if p.suffix.lower() in MESH_SUFFIXES)
    if args.meshes:
        unknown = sorted(set(args.meshes) - {p.stem for p in paths} - {NO_MESH})
        if unknown:
            raise ValueError(f"--meshes: no mesh named {', '.join(unknown)} in {args.meshes_dir} (its meshes: "
                             f"{', '.join(sorted(p.stem for p in paths)) or 'none'}; --meshes {NO_MESH} runs the "
                             "generated shapes alone)")
        paths = [p for p in paths if p.stem in set(args.meshes)]
    if not paths and not args.generated:  # was "no meshes found in ... (names None)"
        raise ValueError(f"no meshes found: nothing to run (--meshes {NO_MESH} and --generated 0: give --generated N)"
                         if args.meshes else f"no meshes found: --meshes-dir {args.meshes_dir} holds no mesh file "
                         f"({', '.join(MESH_SUFFIXES)}) and --generated is 0, so nothing would run")
    if args.generated:
        check_test_seeds(args.generated_first, args.generated)
    grid = Grid(args.n, 3)
    cases = [(p.stem, "mesh", p) for p in paths]
    cases += [(f"gen{seed}", "generated", seed)
              for seed in range(args.generated_first, args.generated_first + args.generated)]
    budgets = sorted({k for ks in args.plan.values() for k in ks})
    tasks = [(label, kind, source, k, noise, name)
             for label, kind, source in cases for k in budgets for noise in args.noise
             for name, ks in args.plan.items()
             if k in ks and (kind == "mesh" or name != "minnorm")]  # minnorm is the meshes' reference only
    rows = []
    print(f"{'mesh':<12} {'dips':>5} {'noise':>6} {'solver':<14} {'IoU':>6} {'Chamfer':>8} {'Hausd.':>7} {'time s':>7} "
          f"{'TV w':>8} verdict", flush=True)
    for row in solved_rows(args, grid, options, tasks):
        rows.append(row)
        weight = "" if row["tv_weight"] is None else f"{row['tv_weight']:8.2e}"
        print(f"{row['mesh']:<12} {row['dips']:>5} {row['noise']:>6} {row['solver']:<14} {row['iou']:6.3f} "
              f"{row['chamfer']:8.4f} {row['hausdorff']:7.4f} {row['seconds']:7.1f} {weight:>8} {row['verdict'] or ''}",
              flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
    print_all(rows, args)
    return rows


def print_all(rows: list[dict], args) -> None:
    """The meshes' summary and, with ``--headline``, the learned prior's (its RESULT line last)."""
    meshes = [r for r in rows if r.get("set", "mesh") == "mesh"]
    if len({r["dips"] for r in meshes}) > 1:
        print_summary(meshes)
    if args.headline:
        print_prior_summary(rows, min(args.budgets), max(args.budgets))


def print_summary(rows: list[dict]) -> None:
    """Means per (solver, budget, noise) and the headline ratio."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["noise"], row["dips"], row["solver"]), []).append(row)
    print(f"\nmeans over meshes\n{'noise':>6} {'dips':>5} {'solver':<9} {'IoU':>6} {'Chamfer':>8} {'Hausd.':>7} "
          f"{'time s':>7} {'meshes':>6}")
    means = {}
    for (noise, k, name), items in sorted(groups.items()):
        m = {key: statistics.fmean(r[key] for r in items) for key in ("iou", "chamfer", "hausdorff", "seconds")}
        means[(noise, k, name)] = m
        print(f"{noise:>6} {k:>5} {name:<9} {m['iou']:6.3f} {m['chamfer']:8.4f} {m['hausdorff']:7.4f} "
              f"{m['seconds']:7.1f} {len(items):>6}")
    budgets = sorted({k for _, k, _ in means})
    optimisers = [s for s in OPTIMISERS if ("clean", budgets[0], s) in means]
    if ("clean", budgets[-1], "minnorm") in means and optimisers and len(budgets) > 1:
        best = min(optimisers, key=lambda s: means[("clean", budgets[0], s)]["chamfer"])
        ratio = means[("clean", budgets[0], best)]["chamfer"] / means[("clean", budgets[-1], "minnorm")]["chamfer"]
        print(f"\nheadline (noise-free): {best} at {budgets[0]} dips / minnorm at {budgets[-1]} dips, "
              f"mean Chamfer ratio = {ratio:.2f} (<= 1 means the {budgets[-1] / budgets[0]:.0f}x saving holds)")
    ratios = mesh_ratios(rows)
    for noise, per_mesh in ratios.items():
        print(f"\nvoxel at {budgets[0]} / minnorm at {budgets[-1]} dips, Chamfer ratio per mesh ({noise}): "
              + ", ".join(f"{mesh} {r:.2f}" for mesh, r in per_mesh.items()))
    summary = {f"voxel{budgets[0]}_over_minnorm{budgets[-1]}_{noise}_{stat}": value
               for noise, per_mesh in ratios.items()
               for stat, value in (("mean", statistics.fmean(per_mesh.values())),
                                   ("median", statistics.median(per_mesh.values())),
                                   ("worst", max(per_mesh.values())))}
    print("RESULT " + " ".join([f"{name}_{noise}_{k}_chamfer={m['chamfer']:.4f}"
                                for (noise, k, name), m in sorted(means.items())]
                               + [f"{key}={value:.3f}" for key, value in summary.items()]))


def mesh_ratios(rows: list[dict]) -> dict[str, dict[str, float]]:
    """``{noise: {mesh: voxel's Chamfer at the smallest budget / minnorm's at the largest}}`` over
    the meshes that have both (``{}`` without voxel and minnorm rows at two budgets)."""
    budgets = sorted({r["dips"] for r in rows})
    chamfer = {(r["noise"], r["mesh"], r["dips"], r["solver"]): r["chamfer"] for r in rows}
    out: dict[str, dict[str, float]] = {}
    if len(budgets) < 2:
        return out
    for noise, mesh, k, name in sorted(chamfer):
        low, high = chamfer.get((noise, mesh, budgets[0], "voxel")), chamfer.get((noise, mesh, budgets[-1], "minnorm"))
        if k == budgets[0] and name == "voxel" and low is not None and high:
            out.setdefault(noise, {})[mesh] = low / high
    return out


def prior_ratios(rows: list[dict], small: int, large: int, noise: str, solver: str = "prior") -> dict[str, float]:
    """Per bundled mesh: ``solver``'s Chamfer at ``small`` dips / minnorm's at ``large`` dips, at ``noise``."""
    chamfer = {(r["mesh"], r["dips"], r["noise"], r["solver"]): r["chamfer"] for r in rows if r["set"] == "mesh"}
    return {mesh: value / chamfer[(mesh, large, n, "minnorm")]
            for (mesh, k, n, name), value in chamfer.items()
            if k == small and n == noise and name == solver and (mesh, large, n, "minnorm") in chamfer}


def print_prior_summary(rows: list[dict], small: int, large: int) -> None:
    """The learned prior's targets (see the module docstring) and the RESULT line."""
    nan = float("nan")
    clean, snr = prior_ratios(rows, small, large, "clean"), prior_ratios(rows, small, large, "snr")
    for label, ratios in (("noise-free", clean), ("noisy", snr)):
        for solver in ("truth", "voxel", "prior", "implicit_prior"):
            r = prior_ratios(rows, small, large, "clean" if label == "noise-free" else "snr", solver)
            if r:
                print(f"{label}: {solver} {small} / minnorm {large} per mesh: "
                      + " ".join(f"{m}={v:.2f}" for m, v in sorted(r.items()))
                      + f"  (median {statistics.median(r.values()):.2f}, worst {max(r.values()):.2f})")
    gen = {(r["mesh"], r["noise"], r["solver"]): r["chamfer"] for r in rows if r["set"] == "generated"
           and r["dips"] == small}
    pairs = [(v, gen[(m, n, "voxel")]) for (m, n, s), v in gen.items() if s == "prior" and (m, n, "voxel") in gen]
    beats = sum(p < v for p, v in pairs) / len(pairs) if pairs else nan
    if pairs:
        print(f"generated shapes: prior below voxel on {sum(p < v for p, v in pairs)} of {len(pairs)}; median "
              f"prior / voxel {statistics.median(p / v for p, v in pairs):.2f}")
    for first, second in (("implicit_prior", "prior"), ("prior", "voxel")):
        both = [(r["chamfer"], s["chamfer"]) for r in rows for s in rows if r["solver"] == first
                and s["solver"] == second and (r["mesh"], r["dips"], r["noise"]) == (s["mesh"], s["dips"], s["noise"])]
        if both:
            print(f"{first} / {second} Chamfer: median {statistics.median(a / b for a, b in both):.2f} "
                  f"over {len(both)} cases")
    seconds = [r["seconds"] for r in rows if r["solver"] in ("prior", "implicit_prior")]
    if seconds:
        print(f"prior solve time: median {statistics.median(seconds):.0f} s, worst {max(seconds):.0f} s")
    median = statistics.median(clean.values()) if clean else nan
    worst = max(clean.values()) if clean else nan
    print(f"RESULT prior{small}_over_minnorm{large}_median={median:.3f} prior{small}_over_minnorm{large}_worst="
          f"{worst:.3f} snr_worst={max(snr.values()) if snr else nan:.3f} beats_voxel_generated={beats:.3f}")


if __name__ == "__main__":
    main()
