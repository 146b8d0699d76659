"""The paper's resolution on a small machine: simulation and reconstruction at 64 / 128 / 240^3.

For every mesh (scaled to ``--fill`` of the working ball), resolution ``N`` and dip budget
(``--fractions`` of ``N^2``, Fibonacci hemisphere), the dips are simulated from the exact mesh
(:func:`~dipnet.simulator.simulate.simulate_measurement`, stage step = one voxel, exact level readings),
timed, and the noisy variant (``--snr`` dB white noise on the same readings) made from the same
scan. Each solver (``minnorm``: matrix-free LSMR when ``B B^T`` would be large; ``voxel``)
reconstructs on the ``auto`` operator (the NUFFT ``fourier`` backend at scale, with
``--eps`` / ``--upsampfac`` / ``--precision``, ``--threads`` threads). Prints one row per run: seconds, the process's
peak resident memory so far (``resource.getrusage``; runs are sequential in one process, so the column
only grows), the CPU seconds of this process (on a shared machine the wall time can be several
times longer), IoU and Chamfer (truth bounding-box diagonals). Ends with

    RESULT sim240_s=<s> minnorm240_s=<s> voxel240_s=<s> voxel128_s=<s> peak_gb=<GB>

holding only the keys that were measured (``simN_s``: simulation of the largest budget of the
first mesh at ``N``; ``minnormN_s`` / ``voxelN_s``: its clean solve). ``--quick``: 128^3 only,
the bunny, 3% of N^2 (492 dips), clean, a 150-step voxel run. Simulated scans are cached in
``--cache``, keyed by their parameters and the simulation code version
(:func:`dipnet.core.code_version.simulation_digest`).

    python scripts/bench_scale.py --quick
    python scripts/bench_scale.py --n 240 --meshes bunny --fractions 0.10 --noise clean
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import resource
import time
from pathlib import Path

import numpy as np
import torch

from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.solvers.checkpoint import Checkpoint
from dipnet.preprocessing.datasets import check_mesh_names, mesh_path
from dipnet.core.code_version import simulation_digest
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.evaluation.metrics import evaluate
from dipnet.operators import make_operator, select_backend
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.simulator.physics import LevelSensor
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import RawScan
from dipnet.shapes import load_mesh
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver
from dipnet.experiments.bench_options import (count_type, grid_size_type, number_type, refuse_bad_run_options,
                                              thread_count)
from dipnet.jobs.cli import user_errors


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="128^3, bunny, 3%% of N^2, clean, short voxel run")
    p.add_argument("--meshes", nargs="+", default=["bunny", "hand"], help="bundled mesh names")
    p.add_argument("--n", type=grid_size_type(3), nargs="+", default=[64, 128, 240], help="grid resolutions N")
    p.add_argument("--fractions", type=number_type("dips per N^2 (a share)", above=0), nargs="+",
                   default=[0.01, 0.03, 0.10], help="dips as a share of N^2")
    p.add_argument("--noise", nargs="+", default=["clean", "snr"], choices=["clean", "snr"])
    p.add_argument("--snr", type=float, default=30.0, help="white-noise SNR in dB for --noise snr")
    p.add_argument("--solvers", nargs="*", default=["minnorm", "voxel"], choices=["minnorm", "voxel"])
    p.add_argument("--fill", type=float, default=0.9, help="mesh radius / working-ball radius")
    p.add_argument("--minnorm-iters", type=count_type(1, "LSMR iterations"), default=60, help="LSMR iteration limit")
    p.add_argument("--voxel-iters", type=count_type(1, "voxel solver steps"), default=200, help="voxel solver steps")
    p.add_argument("--eps", type=number_type("NUFFT tolerance", above=0),
                   default=1e-3, help="NUFFT tolerance of the fourier operator")
    p.add_argument("--upsampfac", type=number_type("NUFFT oversampling", above=1),
                   default=1.25, help="NUFFT oversampling of the fourier operator")
    p.add_argument("--precision", choices=["single", "double"], default="single",
                   help="NUFFT arithmetic of the fourier operator (single: 1.65x faster at eps 1e-3)")
    p.add_argument("--threads", type=thread_count, default=1,
                   help="torch and NUFFT threads (2 on a quiet 2-core machine)")
    p.add_argument("--cache", type=Path, default=Path("outputs/bench_scale_cache"), help="simulated scans")
    p.add_argument("--json", type=Path, help="also write every row to this JSON file")
    p.add_argument("--checkpoint-dir", type=Path, help="checkpoint the voxel solves here (and resume from it)")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), n=[128], meshes=["bunny"], fractions=[0.03], noise=["clean"],
                    voxel_iters=150)
    try:
        check_mesh_names(args.meshes)
    except FileNotFoundError as exc:  # now, not after the meshes before it
        p.error(f"--meshes: {exc}")
    refuse_bad_run_options(p, args)  # --snr, --fill, --json: now, not at the first noisy case or after the run
    return args


def peak_gb() -> float:
    """Peak resident memory of this process so far, GB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def noisy_copy(raw: RawScan, snr_db: float, seed: int = 0) -> RawScan:
    """The same dips read by a level sensor with white noise at ``snr_db`` (see :class:`LevelSensor`)."""
    sensor = LevelSensor(snr_db=snr_db, seed=seed)
    out = copy.deepcopy(raw)
    for o in out.orientations:
        o.values, sigma = sensor.read(o.values, o.time_s, np.random.default_rng([seed, o.k]))
        o.meta["noise_sigma"] = sigma
    return out


def simulate(args, shape, grid: Grid, k: int) -> tuple[dict[str, DipMeasurement], float]:
    """Clean and noisy measurements for ``k`` dips on ``grid`` and the simulation seconds (0 if cached)."""
    tag = f"{shape.name}_n{grid.n}_k{k}_f{args.fill}_code{simulation_digest()}"
    files = {noise: args.cache / f"{tag}_{noise}{args.snr if noise == 'snr' else ''}.npz" for noise in args.noise}
    if all(f.is_file() for f in files.values()):
        return {noise: DipMeasurement.load(f) for noise, f in files.items()}, 0.0
    started = time.perf_counter()
    raw, clean = simulate_measurement(shape, fibonacci_hemisphere(k), grid=grid, step_mm=grid.voxel_size,
                                      sensor=LevelSensor(), progress=False)
    seconds = time.perf_counter() - started
    out = {}
    for noise, f in files.items():
        out[noise] = clean if noise == "clean" else preprocess(noisy_copy(raw, args.snr), grid=grid, t_start="metadata")
        args.cache.mkdir(parents=True, exist_ok=True)
        out[noise].save(f)
    return out, seconds


def operator_for(args, grid: Grid, directions: torch.Tensor):
    """The ``auto`` backend; the fourier one with the benchmark's NUFFT accuracy."""
    backend = select_backend(grid, len(directions))
    options = ({"eps": args.eps, "upsampfac": args.upsampfac, "single": args.precision == "single"}
               if backend == "fourier" else {})
    return make_operator(grid, directions, grid.n, backend=backend, **options)


def make_solver(args, name: str, tag: str):
    if name == "minnorm":
        return MinNormSolver(iter_lim=args.minnorm_iters, progress=False)
    checkpoint = Checkpoint(args.checkpoint_dir / tag, every=10) if args.checkpoint_dir else None
    return VoxelSolver(iterations=args.voxel_iters, progress=True, checkpoint=checkpoint)


def main(argv=None) -> dict[str, float]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> dict[str, float]:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    result: dict[str, float] = {}
    rows = []
    print(f"{'mesh':<7} {'N':>4} {'dips':>5} {'noise':>6} {'step':<8} {'seconds':>8} {'cpu s':>7} {'peak GB':>7} "
          f"{'IoU':>6} {'Chamfer':>8} {'method':<8}", flush=True)
    for n in args.n:
        grid = Grid(n, 3)
        for m_index, name in enumerate(args.meshes):
            shape = load_mesh(mesh_path(name), radius=args.fill * grid.radius)
            truth = shape.occupancy(grid, supersample=2 if n <= 128 else 1).numpy()
            for f_index, fraction in enumerate(args.fractions):
                k = math.ceil(fraction * n * n)
                headline = m_index == 0 and f_index == len(args.fractions) - 1
                cpu = time.process_time()
                measurements, sim_s = simulate(args, shape, grid, k)
                row = {"mesh": name, "n": n, "dips": k, "noise": "-", "step": "simulate", "seconds": sim_s,
                       "cpu_s": time.process_time() - cpu, "peak_gb": peak_gb()}
                rows.append(row)
                print(f"{name:<7} {n:>4} {k:>5} {'-':>6} {'simulate':<8} {sim_s:8.1f} {row['cpu_s']:7.1f} "
                      f"{row['peak_gb']:7.2f}{' (cached)' if sim_s == 0 else ''}", flush=True)
                if headline and sim_s > 0:
                    result[f"sim{n}_s"] = sim_s
                operator = operator_for(args, grid, measurements["clean" if "clean" in measurements else "snr"]
                                        .directions)
                for noise, measurement in measurements.items():
                    for solver_name in args.solvers:
                        started, cpu = time.perf_counter(), time.process_time()
                        tag = f"{name}_n{n}_k{k}_{noise}"
                        recon = make_solver(args, solver_name, tag).solve(measurement, operator)
                        seconds, cpu = time.perf_counter() - started, time.process_time() - cpu
                        scores = evaluate(recon, truth, grid, truth_mesh=shape.mesh)
                        row = {"mesh": name, "n": n, "dips": k, "noise": noise, "step": solver_name,
                               "seconds": seconds, "cpu_s": cpu, "peak_gb": peak_gb(), "iou": scores["iou"],
                               "chamfer": scores["chamfer"], "method": recon.info.get("method", "adam")}
                        rows.append(row)
                        print(f"{name:<7} {n:>4} {k:>5} {noise:>6} {solver_name:<8} {seconds:8.1f} {cpu:7.1f} "
                              f"{row['peak_gb']:7.2f} {row['iou']:6.3f} {row['chamfer']:8.4f} {row['method']:<8}",
                              flush=True)
                        if headline and noise == "clean":
                            result[f"{solver_name}{n}_s"] = seconds
    result["peak_gb"] = peak_gb()
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print("RESULT " + " ".join(f"{key}={value:.1f}" if key != "peak_gb" else f"{key}={value:.2f}"
                               for key, value in result.items()), flush=True)
    return result


if __name__ == "__main__":
    main()
