"""Adaptive (next-best-dip) plans against fixed plans, on the bundled meshes (not a timed test).

For every mesh (scaled to ``--fill`` of the working ball) on an ``--n``^3 grid, dips simulated
from the mesh geometry with level-sensor noise at ``--snr`` dB:

* full hemisphere: Fibonacci ``--budget`` and Fibonacci ``--large`` dips, against the adaptive
  loop (:func:`dipnet.planning.adaptive.adaptive_loop`) from ``--initial`` Fibonacci-like dips to
  ``--budget`` in batches of ``--batch``;
* tilt limited to ``--cap-tilt`` degrees (the authors' rig): the uniform plan over the
  reachable cap with ``--budget`` dips against the adaptive loop restricted to the cap;
* with ``--oracle R``, a bound on what any choice of ``--budget`` directions gains: the Fibonacci
  plan and ``R`` random rotations of it, each reconstructed, and the one with the lowest Chamfer
  against the *true* shape kept (a planner that knows the answer; its row also gives the spread);
* with ``--oracle-pool P``, the adaptive loop with a planner that knows the answer, on the
  hemisphere and on the cap: each next dip is the one, among ``P`` random reachable candidates,
  whose addition gives the reconstruction with the lowest Chamfer against the true shape (greedy;
  any plan, not only well-spread ones).

Every final reconstruction uses ``--solver`` (default voxel: at 41 dips and 30 dB it ties with
implicit, 4x faster, and beats minnorm 4x in Chamfer, docs/guide/solvers.md);
the loop's intermediate reconstructions use ``--plan-solver``, by default the same: with minnorm
estimates the planner's noise level is their model error and it plans no better than a uniform
plan (:mod:`dipnet.planning.planner`). With the same solver the loop's last reconstruction is the final
one. The planner's posterior grid is half the reconstruction's. Prints one row per mesh and plan (IoU,
Chamfer / bbox diagonal, dips, seconds; for adaptive runs also the planning seconds per step),
the means, the uncertainty calibration (error rate per uncertainty decile, pooled) and ends with

    RESULT adaptive41_over_fib123=<ratio of mean Chamfer> adaptive41_over_fib41=<ratio>
        cap_adaptive_over_uniform=<ratio>

(with ``--oracle``, also ``oracle_rotations41_over_fib123=<ratio>``; with ``--oracle-pool``,
``oracle_greedy41_over_fib123=<ratio> cap_oracle_greedy_over_uniform=<ratio>``).

    python scripts/bench_planning.py --quick          # 2 meshes, 32^3, one process per mesh: a few minutes
    python scripts/bench_planning.py --jobs 2         # every bundled mesh at 64^3, two meshes at a time
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dipnet.planning.adaptive import AdaptiveSettings, adaptive_loop
from dipnet.simulator.source import SimulatedDips, concatenate
from dipnet.preprocessing.datasets import check_mesh_names, mesh_names, mesh_path
from dipnet.core.grid import Grid
from dipnet.evaluation.metrics import evaluate
from dipnet.experiments.bench_options import count_type, refuse_bad_run_options, thread_count
from dipnet.operators import make_operator
from dipnet.core.orientations import Reach, fibonacci_hemisphere
from dipnet.simulator.physics import LevelSensor
from dipnet.planning.planner import NextBestDipPlanner, Planner
from dipnet.shapes import load_mesh
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver
from dipnet.evaluation.uncertainty import calibration_by_decile, uncertainty

SOLVERS = {"minnorm": MinNormSolver, "voxel": VoxelSolver}
QUICK_MESHES = ["bunny", "part_B13"]  # light meshes: simulating dips costs about O(faces)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", nargs="*", help="bundled mesh names; default all (--quick: bunny, part_B13)")
    p.add_argument("--n", type=int, default=None, help="grid resolution N (default 64; --quick 32)")
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR in dB")
    p.add_argument("--initial", type=int, default=8, help="dips before the first plan")
    p.add_argument("--budget", type=int, default=41, help="dips of the adaptive and the small fixed plans")
    p.add_argument("--large", type=int, default=123, help="dips of the large Fibonacci plan")
    p.add_argument("--batch", type=int, default=8, help="dips planned per step")
    p.add_argument("--cap-tilt", type=float, default=35.0, help="largest tilt of the limited rig (degrees)")
    p.add_argument("--solver", choices=list(SOLVERS), default="voxel", help="solver of every final reconstruction")
    p.add_argument("--plan-solver", choices=list(SOLVERS), default="voxel",
                   help="solver of the loop's intermediate reconstructions")
    p.add_argument("--fill", type=float, default=0.9, help="mesh radius / working-ball radius")
    p.add_argument("--threads", type=thread_count, default=1, help="torch threads per process")
    p.add_argument("--jobs", type=int, default=None, help="meshes benchmarked in parallel processes (default 1; "
                   "--quick: 2, one per core)")
    p.add_argument("--oracle", type=count_type(0, "random rotations"), default=0, metavar="R",
                   help="also the best of the Fibonacci plan and R random rotations of it, chosen with the true shape")
    p.add_argument("--oracle-pool", type=count_type(0, "candidates per dip"), default=0, metavar="P",
                   help="also the adaptive loop with a greedy planner that knows the true shape, trying P candidates "
                        "per dip")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="2 meshes at 32^3")
    p.add_argument("--json", type=Path, help="also write every row to this JSON file")
    args = p.parse_args(argv)
    args.n = args.n or (32 if args.quick else 64)
    args.meshes = args.meshes or (QUICK_MESHES if args.quick else mesh_names())
    if args.jobs is not None and args.jobs < 1:  # was taken as the default (0) or as 1 (-3), unsaid
        p.error(f"--jobs must be 1 or more (meshes benchmarked at once), got {args.jobs}")
    args.jobs = args.jobs or (2 if args.quick else 1)
    try:
        check_mesh_names(args.meshes)
    except FileNotFoundError as exc:  # now, not after the meshes before it
        p.error(f"--meshes: {exc}")
    check_plan_options(p, args)
    return args


def check_plan_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (``p.error``: one line, exit 2) before any mesh what a case would fail on after minutes of solves, or
    run on without a word: ``--fill`` outside (0, 1] (a mesh larger than the working ball, which the grid cannot
    hold), the loop's ``--budget`` / ``--batch`` / ``--initial``, the ``--cap-tilt`` reach, ``--large`` or ``--n``,
    and the run options ``--snr``, ``--seed``, ``--threads``, ``--json``
    (:func:`~dipnet.experiments.bench_options.check_run_options`: ``--threads 0`` and ``--snr nan`` were tracebacks
    from the worker processes, after the first mesh's plans)."""
    refuse_bad_run_options(p, args)  # --fill among them
    try:
        Grid(args.n, 3)
        AdaptiveSettings(budget=args.budget, batch_size=args.batch, initial_dips=args.initial)
        Reach(tilt_range_deg=(0.0, args.cap_tilt), step_deg=5.0)
        fibonacci_hemisphere(args.large)
    except ValueError as exc:
        p.error(f"--n {args.n}, --budget {args.budget}, --batch {args.batch}, --initial {args.initial}, --cap-tilt "
                f"{args.cap_tilt:g}, --large {args.large}: {exc}")


def main(argv=None) -> dict[str, float]:
    args = parse_args(argv)
    print(f"{'mesh':<12} {'plan':<16} {'dips':>5} {'IoU':>6} {'Chamfer':>8} {'time s':>7} {'plan s/step':>11}",
          flush=True)
    if args.jobs > 1:  # one process per mesh, each with its own torch threads
        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("fork")) as pool:
            per_mesh = list(pool.map(bench_mesh, args.meshes, [args] * len(args.meshes)))
    else:
        per_mesh = [bench_mesh(name, args) for name in args.meshes]
    rows = [row for mesh_rows, _ in per_mesh for row in mesh_rows]
    calibration = [mesh_calibration for _, mesh_calibration in per_mesh]
    result = summarise(rows, calibration, args)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return result


def bench_mesh(name: str, args: argparse.Namespace) -> tuple[list[dict], np.ndarray]:
    """Every plan on one mesh: its rows (printed as they come) and the uncertainty calibration
    (error rate per ``p_wrong`` decile) of the Fibonacci plan's reconstruction."""
    torch.set_num_threads(args.threads)
    grid = Grid(args.n, 3)
    hemisphere, cap = Reach(), Reach(tilt_range_deg=(0.0, args.cap_tilt), step_deg=5.0)
    sensor = LevelSensor(snr_db=args.snr, quantum_mm=0.0, seed=args.seed)

    def simulate(shape, directions, **kw):
        return simulate_measurement(shape, directions, sensor=sensor, **kw)

    def solve(measurement, name):
        operator = make_operator(grid, measurement.directions, grid.n)
        return SOLVERS[name](progress=False).solve(measurement, operator), operator

    rows, calibration = [], None
    shape = load_mesh(mesh_path(name), radius=args.fill * grid.radius)
    truth = shape.occupancy(grid, supersample=3).numpy() >= 0.5
    plans = {"fibonacci": fibonacci_hemisphere(args.budget), "fibonacci_large": fibonacci_hemisphere(args.large),
             "cap_uniform": cap.uniform(args.budget), "adaptive": hemisphere, "cap_adaptive": cap}
    if args.oracle:
        plans["oracle_rotations"] = rotated_plans(fibonacci_hemisphere(args.budget), args.oracle, args.seed)
    if args.oracle_pool:
        plans["oracle_greedy"], plans["cap_oracle_greedy"] = hemisphere, cap
    for plan, what in plans.items():
        t0 = time.perf_counter()
        plan_seconds: list[float] = []
        spread = None
        acquire = SimulatedDips(simulate, shape, grid, grid.n, args.seed)
        if isinstance(what, Reach):
            settings = AdaptiveSettings(budget=args.budget, batch_size=args.batch, initial_dips=args.initial)
            planner = NextBestDipPlanner(resolution=args.n // 2, seed=args.seed) if "oracle" not in plan else \
                OraclePlanner(lambda m: solve(m, args.solver)[0],
                              lambda r: evaluate(r, truth, grid, truth_mesh=shape.mesh)["chamfer"],
                              lambda d: simulate(shape, d, grid=grid, n_slabs=grid.n, seed=args.seed + 1)[1],
                              args.oracle_pool, args.seed)
            result = adaptive_loop(acquire, lambda m: solve(m, args.plan_solver), planner, what, settings)
            plan_seconds = [h["plan_seconds"] for h in result.history if "plan_seconds" in h]
            measurement = result.measurement
            # the loop's last reconstruction is the final one when it used the final solver
            recon, operator = (result.reconstruction, result.operator) if args.plan_solver == args.solver else \
                solve(measurement, args.solver)
        elif isinstance(what, list):  # the oracle: every plan reconstructed, the best against the truth kept
            tried = []
            for directions in what:
                measurement = SimulatedDips(simulate, shape, grid, grid.n, args.seed)(directions)
                recon, operator = solve(measurement, args.solver)
                tried.append((evaluate(recon, truth, grid, truth_mesh=shape.mesh), measurement, recon, operator))
            chamfers = sorted(t[0]["chamfer"] for t in tried)
            spread = [chamfers[0], statistics.median(chamfers), chamfers[-1]]
            scores, measurement, recon, operator = min(tried, key=lambda t: t[0]["chamfer"])
        else:
            measurement = acquire(what)
            recon, operator = solve(measurement, args.solver)
        seconds = time.perf_counter() - t0
        if spread is None:
            scores = evaluate(recon, truth, grid, truth_mesh=shape.mesh)
        row = {"mesh": name, "plan": plan, "dips": measurement.n_orientations, "iou": scores["iou"],
               "chamfer": scores["chamfer"], "seconds": seconds,
               "plan_seconds_per_step": statistics.fmean(plan_seconds) if plan_seconds else None,
               "chamfer_min_median_max": spread}
        if plan == "fibonacci":
            maps, _ = uncertainty(recon, measurement, operator)
            calibration = calibration_by_decile(maps["p_wrong"], recon.binary, truth)
        rows.append(row)
        step = f"{row['plan_seconds_per_step']:11.2f}" if plan_seconds else f"{'':>11}"
        tail = f"  Chamfer of the {len(what)} plans: min / median / max " + " / ".join(f"{c:.4f}" for c in spread) \
            if spread else ""
        print(f"{name:<12} {plan:<16} {row['dips']:>5} {row['iou']:6.3f} {row['chamfer']:8.4f} {seconds:7.1f} {step}"
              + tail, flush=True)
    return rows, calibration


class OraclePlanner(Planner):
    """Greedy planner that knows the answer (a bound, not a method): each next dip is the one among
    ``pool`` random candidates whose addition gives the lowest ``error`` of ``reconstruct``.

    Args:
        reconstruct: measurement -> reconstruction (the final solver).
        error: reconstruction -> its error against the true shape (Chamfer).
        dip: direction ``(1, 3)`` -> the measurement of that one dip (its own noise).
        pool, seed: candidates tried per dip, and the seed that draws them.
    """

    def __init__(self, reconstruct, error, dip, pool: int, seed: int) -> None:
        self.reconstruct, self.error, self.dip, self.pool = reconstruct, error, dip, pool
        self.rng = np.random.default_rng(seed)

    def next(self, measurement, reconstruction, candidates, k=1, operator=None, posterior=None) -> torch.Tensor:
        picked, current = [], measurement
        for _ in range(k):
            trials = []
            for i in self.rng.choice(len(candidates), size=min(self.pool, len(candidates)), replace=False):
                trial = concatenate(current, self.dip(candidates[i:i + 1]))
                trials.append((self.error(self.reconstruct(trial)), int(i), trial))
            _, best, current = min(trials, key=lambda t: t[0])
            picked.append(candidates[best])
        return torch.stack(picked)


def rotated_plans(plan: torch.Tensor, count: int, seed: int) -> list[torch.Tensor]:
    """``plan`` ``(k, 3)`` and ``count`` copies of it under random rotations (seeded), folded onto the
    upper hemisphere (a dip along ``-d`` measures the slabs along ``d``): as well spread, placed anew."""
    turns = Rotation.random(count, random_state=seed).as_matrix()
    plans = [plan]
    for turn in torch.as_tensor(turns, dtype=torch.float64):
        d = plan @ turn.T
        plans.append(d * torch.where(d[:, 2:] < 0, -1.0, 1.0))
    return plans


def summarise(rows: list[dict], calibration: list[np.ndarray], args) -> dict[str, float]:
    """Means per plan, the pooled calibration and the RESULT line."""
    means = {}
    print(f"\nmeans over {len(args.meshes)} meshes ({args.n}^3, {args.snr:g} dB, solver {args.solver}, "
          f"plan solver {args.plan_solver})\n{'plan':<16} {'dips':>5} {'IoU':>6} {'Chamfer':>8} {'time s':>7}")
    for plan in dict.fromkeys(r["plan"] for r in rows):
        items = [r for r in rows if r["plan"] == plan]
        means[plan] = {k: statistics.fmean(r[k] for r in items) for k in ("iou", "chamfer", "seconds", "dips")}
        m = means[plan]
        print(f"{plan:<16} {m['dips']:5.0f} {m['iou']:6.3f} {m['chamfer']:8.4f} {m['seconds']:7.1f}")
    steps = [r["plan_seconds_per_step"] for r in rows if r["plan"] in ("adaptive", "cap_adaptive")]
    print(f"\nplanning: {statistics.fmean(steps):.2f} s per step on average, at most {max(steps):.2f} s")
    deciles = np.nanmean(np.stack(calibration), axis=0)
    print("uncertainty calibration (Fibonacci plan, mean over meshes): error rate per p_wrong decile, lowest first:\n  "
          + " ".join(f"{v:.3f}" for v in deciles))
    ratios = {"adaptive41_over_fib123": means["adaptive"]["chamfer"] / means["fibonacci_large"]["chamfer"],
              "adaptive41_over_fib41": means["adaptive"]["chamfer"] / means["fibonacci"]["chamfer"],
              "cap_adaptive_over_uniform": means["cap_adaptive"]["chamfer"] / means["cap_uniform"]["chamfer"]}
    for oracle in ("oracle_rotations", "oracle_greedy"):
        if oracle in means:
            ratios[f"{oracle}41_over_fib123"] = means[oracle]["chamfer"] / means["fibonacci_large"]["chamfer"]
    if "cap_oracle_greedy" in means:
        ratios["cap_oracle_greedy_over_uniform"] = (means["cap_oracle_greedy"]["chamfer"]
                                                    / means["cap_uniform"]["chamfer"])
    print("RESULT " + " ".join(f"{k}={v:.3f}" for k, v in ratios.items()))
    return ratios


if __name__ == "__main__":
    main()
