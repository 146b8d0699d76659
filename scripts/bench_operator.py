"""Benchmark the dip operator backends (not a test): speed, peak memory and accuracy.

Each case (backend, N, K) runs in a fresh subprocess, so the peak resident memory
(``ru_maxrss``, including the ~0.3 GB of the Python + torch interpreter) belongs to that case
alone; a case is stopped (and marked so) when its memory exceeds ``--memory-limit`` GB.
Backends whose ``O(K N^d)`` case time (setup + one forward + adjoint), extrapolated linearly
in K from a K=20 run, would exceed ``--limit`` seconds are skipped and marked so, with the
extrapolated forward + adjoint time (optimistic for splat, whose weight cache fits in memory
only at small K). Accuracy is the relative L2 error of the profiles of a partial-volume ball
against its exact slab volumes.

    python scripts/bench_operator.py            # 3D table, 2D vs skimage radon
    python scripts/bench_operator.py --quick    # N=64, K in {100, 1000}, 2D at 128^2
    python scripts/bench_operator.py --lsqr     # 128^3 LSQR reconstruction from 1600 dips
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from dipnet.experiments.bench_options import count_type, grid_size_type, number_type
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.jobs.cli import user_errors
from dipnet.core.grid import Grid
from dipnet.operators import BACKENDS, make_operator
from dipnet.operators.analytic import ball_occupancy, ball_profiles
from dipnet.core.orientations import make_directions

CALIBRATION_K = 20
REPEATS = 3


def _ball(grid: Grid) -> tuple[torch.Tensor, torch.Tensor, float]:
    centre = torch.tensor([6.0, -4.0, 3.0][: grid.ndim], dtype=torch.float64) * grid.extent / 100
    radius = 0.3 * grid.extent
    return ball_occupancy(grid, centre, radius), centre, radius


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def run_case(backend: str, ndim: int, n: int, k: int) -> dict:
    """Time forward + adjoint (after a warm-up that builds plans / caches) in this process."""
    grid = Grid(n, ndim)
    dirs = make_directions("fibonacci", k, ndim)
    vol, centre, radius = _ball(grid)
    t0 = time.perf_counter()
    op = make_operator(grid, dirs, backend=backend)
    prof = op(vol)
    op.adjoint(prof)
    setup = time.perf_counter() - t0
    fwd = adj = math.inf
    for _ in range(REPEATS if setup < 1.0 else 1):  # best of a few for the short cases
        t0 = time.perf_counter()
        prof = op(vol)
        t1 = time.perf_counter()
        op.adjoint(prof)
        fwd, adj = min(fwd, t1 - t0), min(adj, time.perf_counter() - t1)
    return {"backend": backend, "ndim": ndim, "n": n, "k": k, "setup_s": setup, "forward_s": fwd,
            "adjoint_s": adj, "seconds": fwd + adj,
            "rel_error": _rel(prof, ball_profiles(op.directions, op.slab_edges(), centre, radius)),
            "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def run_radon_case(n: int, k: int) -> dict:
    """2D: the Fourier backend against ``skimage.transform.radon`` on the same angles."""
    from skimage.transform import radon

    grid = Grid(n, 2)
    angles = np.arange(k) * 180.0 / k
    dirs = make_directions("uniform", k, 2)
    vol, centre, radius = _ball(grid)
    op = make_operator(grid, dirs, backend="fourier")
    op(vol)  # plan
    t0 = time.perf_counter()
    prof = op(vol)
    ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    sino = radon(vol.numpy(), theta=-angles, circle=True)  # skimage's angle runs the other way
    theirs = time.perf_counter() - t0
    # skimage bin i is centred at t = (i - n//2) h + (h/2)(cos a + sin a) (rotation about pixel n//2):
    # bin the line integrals into our slabs through the piecewise-linear cumulative area.
    h = grid.voxel_size
    edges = op.slab_edges().numpy()
    binned = np.empty((k, op.n_slabs))
    for j in range(k):
        centre_t = (np.arange(n) - n // 2) * h + h / 2 * float(dirs[j].sum())
        cum = np.concatenate([[0.0], np.cumsum(sino[:, j] * h * h)])
        binned[j] = np.diff(np.interp(edges, np.concatenate([centre_t - h / 2, centre_t[-1:] + h / 2]), cum))
    truth = ball_profiles(op.directions, op.slab_edges(), centre, radius)
    return {"n": n, "k": k, "fourier_s": ours, "radon_s": theirs,
            "rel_diff": _rel(torch.from_numpy(binned), prof), "fourier_err": _rel(prof, truth),
            "radon_err": _rel(torch.from_numpy(binned), truth)}


def _rss_gb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 2**20


def _subprocess(args: list[str], memory_gb: float = math.inf) -> dict:
    """Run this script with ``args`` in a fresh interpreter; stop it (and say so) above ``memory_gb``."""
    proc = subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)
    while proc.poll() is None:
        try:
            if _rss_gb(proc.pid) > memory_gb:
                proc.kill()
                proc.wait()
                return {"stopped_gb": memory_gb}
        except (FileNotFoundError, StopIteration):
            pass
        time.sleep(0.1)
    if proc.returncode:
        raise RuntimeError(f"benchmark case {args} failed with exit code {proc.returncode}")
    return json.loads(proc.stdout.read().strip().splitlines()[-1])


def _case(backend: str, ndim: int, n: int, k: int, memory_gb: float = math.inf) -> dict:
    row = _subprocess(["--worker", json.dumps([backend, ndim, n, k])], memory_gb)
    return {"backend": backend, "n": n, "k": k, **row}


def _extrapolate(backend: str, n: int) -> dict:
    """Per-orientation seconds of an ``O(K N^d)`` backend from a small-K run: ``case_s`` (setup
    + one forward + adjoint, decides skipping) and ``run_s`` (forward + adjoint, for the speed-up)."""
    cal = _case(backend, 3, n, CALIBRATION_K)
    return {"case_s": (cal["setup_s"] + cal["seconds"]) / CALIBRATION_K, "run_s": cal["seconds"] / CALIBRATION_K}


def bench_table(sizes: list[int], counts: list[int], backends: list[str], limit: float, memory: float) -> list[dict]:
    rows = []
    for n in sizes:
        linear = {b: _extrapolate(b, n) for b in backends if b != "fourier"}
        for k in counts:
            for b in backends:
                cost = linear.get(b)
                if cost and cost["case_s"] * k > limit:
                    row = {"backend": b, "n": n, "k": k, "skipped": True, "estimate_s": cost["run_s"] * k}
                else:
                    row = _case(b, 3, n, k, memory)
                rows.append(row)
                print(_format_row(row, rows), flush=True)
    return rows


def _format_row(row: dict, rows: list[dict]) -> str:
    head = f"| {row['n']:>4} | {row['k']:>5} | {row['backend']:<10} |"
    if row.get("skipped"):
        return head + f" skipped (extrapolated from K={CALIBRATION_K}: {row['estimate_s']:.0f} s) | | | |"
    if "stopped_gb" in row:
        return head + f" stopped: > {row['stopped_gb']:.1f} GB | | | |"
    reference_s, how = reference_time(rows, row["n"], row["k"])
    ref = {r["backend"]: r for r in rows if r["n"] == row["n"] and r["k"] == row["k"]}
    if how == "measured":
        speed = f"{reference_s / row['seconds']:.0f}x"
    elif "seconds" in ref.get("splat", {}):
        speed = f"{ref['splat']['seconds'] / row['seconds']:.1f}x vs splat"
    elif how == "extrapolated":
        speed = f"{reference_s / row['seconds']:.0f}x vs extrapolated rotate_sum"
    else:
        speed = "-"
    return head + (f" {row['seconds']:.3f} (fwd {row['forward_s']:.3f}, setup {row['setup_s']:.2f}) | {speed} |"
                   f" {row['peak_gb']:.2f} | {row['rel_error']:.2e} |")


def scaling(rows: list[dict]) -> list[str]:
    """Log-log slopes of the Fourier backend's time in K (largest two K) and in N (per K)."""
    f = {(r["n"], r["k"]): r["seconds"] for r in rows if r["backend"] == "fourier" and "seconds" in r}
    sizes, counts = sorted({n for n, _ in f}), sorted({k for _, k in f})
    lines = []
    for n in sizes:
        for k0, k1 in zip(counts, counts[1:]):
            lines.append(f"fourier N={n}: K {k0}->{k1}: time x{f[n, k1] / f[n, k0]:.2f} "
                         f"(K^{math.log(f[n, k1] / f[n, k0]) / math.log(k1 / k0):.2f})")
    for k in counts:
        for n0, n1 in zip(sizes, sizes[1:]):
            lines.append(f"fourier K={k}: N {n0}->{n1}: time x{f[n1, k] / f[n0, k]:.2f} "
                         f"(N^{math.log(f[n1, k] / f[n0, k]) / math.log(n1 / n0):.2f})")
    return lines


def bench_lsqr(n: int, k: int, iterations: int) -> dict:
    """Least-squares reconstruction of the ball from ``k`` dips by scipy LSQR (matrix-free)."""
    import scipy.sparse.linalg

    grid = Grid(n)
    vol, _, _ = _ball(grid)
    t0 = time.perf_counter()
    op = make_operator(grid, make_directions("fibonacci", k, 3))
    b = op(vol).reshape(-1).numpy()
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    x, _, itn, rnorm = scipy.sparse.linalg.lsqr(op.as_linear_operator(), b, iter_lim=iterations)[:4]
    wall = time.perf_counter() - t0
    rec = torch.from_numpy(x).reshape(grid.shape) > 0.5
    truth = vol > 0.5
    iou = float((rec & truth).sum() / (rec | truth).sum())
    return {"n": n, "k": k, "backend": type(op).__name__, "setup_s": setup, "lsqr_s": wall, "iterations": int(itn),
            "rel_residual": float(rnorm / np.linalg.norm(b)), "iou": iou,
            "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def parse_args(argv=None) -> argparse.Namespace:
    """The options, each refused before any case when no case could use it (one line naming it, exit 2): ``--sizes``
    and ``--radon-size`` (but 0) no grid takes, ``--orientations`` below 1, ``--limit`` / ``--memory-limit`` not a
    positive number (``nan`` skipped nothing, ``0`` every case), ``--lsqr-iterations`` below 1."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=grid_size_type(3), nargs="+", default=[64, 128], help="grid sizes N (3D)")
    parser.add_argument("--orientations", type=count_type(1, "dips"), nargs="+", default=[100, 1000, 5000],
                        help="counts K")
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    parser.add_argument("--limit", type=number_type("seconds", above=0, no_limit=True), default=60.0,
                        help="skip cases estimated above this (s)")
    parser.add_argument("--memory-limit", type=number_type("GB", above=0, no_limit=True), default=12.0,
                        help="skip cases estimated above this (GB)")
    parser.add_argument("--radon-size", type=grid_size_type(2, zero="skip"), default=256,
                        help="2D grid for the skimage comparison (0: skip)")
    parser.add_argument("--quick", action="store_true", help="N=64, K in {100, 1000}, 2D at 128^2")
    parser.add_argument("--lsqr", action="store_true", help="only the 128^3 / 1600-dip LSQR timing")
    parser.add_argument("--lsqr-iterations", type=count_type(1, "LSQR iterations"), default=40)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--radon-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(parser, argv), sizes=[64], orientations=[100, 1000], radon_size=128)
    return args


def main(argv=None) -> None:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        run(argv)


def run(argv=None) -> None:
    args = parse_args(argv)
    if args.worker:
        print(json.dumps(run_case(*json.loads(args.worker))))
        return
    if args.radon_worker:
        print(json.dumps(run_radon_case(*json.loads(args.radon_worker))))
        return
    print(f"# {os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}, load average {os.getloadavg()}")
    if args.lsqr:
        print(json.dumps(bench_lsqr(128, 1600, args.lsqr_iterations)))
        return
    print("|    N |     K | backend    | forward + adjoint (s) | speed-up | peak RSS (GB) | ball rel. L2 |")
    print("|------|-------|------------|-----------------------|----------|---------------|--------------|")
    rows = bench_table(args.sizes, args.orientations, args.backends, args.limit, args.memory_limit)
    if "fourier" in args.backends:
        print("\n".join(scaling(rows)))
    if args.radon_size:
        print("\n2D vs skimage.transform.radon (forward only, same angles):")
        print("| N | K | fourier (s) | radon (s) | radon / fourier | rel. diff binned | err fourier | err radon |")
        print("|---|---|-------------|-----------|-----------------|------------------|-------------|-----------|")
        for k in (180, 1000):
            r = _subprocess(["--radon-worker", json.dumps([args.radon_size, k])])
            print(f"| {r['n']} | {r['k']} | {r['fourier_s']:.3f} | {r['radon_s']:.3f} | "
                  f"{r['radon_s'] / r['fourier_s']:.1f}x | {r['rel_diff']:.2e} | {r['fourier_err']:.2e} | "
                  f"{r['radon_err']:.2e} |", flush=True)
    print(f"# load average at the end {os.getloadavg()}")
    print(result_line(rows))


def reference_time(rows: list[dict], n: int, k: int) -> tuple[float | None, str]:
    """Seconds of the ``rotate_sum`` reference at ``(n, k)`` and how they were had: ``"measured"``,
    ``"extrapolated"`` (the case was skipped: linear in K from a K=20 run) or ``"none"`` (not run)."""
    ref = next((r for r in rows if r["backend"] == "rotate_sum" and (r["n"], r["k"]) == (n, k)), {})
    if "seconds" in ref:
        return ref["seconds"], "measured"
    if "estimate_s" in ref:
        return ref["estimate_s"], "extrapolated"
    return None, "none"


def result_line(rows: list[dict]) -> str:
    """``RESULT`` of the largest measured fourier case: its seconds, peak memory and speed-up over the
    reference, with ``rotate_sum_time=measured|extrapolated|none`` saying where the reference time
    came from (extrapolated linearly in K from a K=20 run when the reference case was skipped)."""
    timed = [r for r in rows if r["backend"] == "fourier" and "seconds" in r]
    if not timed:
        return "RESULT fourier_cases=0"
    top = max(timed, key=lambda r: (r["n"], r["k"]))
    reference_s, how = reference_time(rows, top["n"], top["k"])
    speed = f"{reference_s / top['seconds']:.0f}" if reference_s else "nan"
    return (f"RESULT n={top['n']} k={top['k']} fourier_s={top['seconds']:.3f} peak_gb={top['peak_gb']:.2f} "
            f"speedup_vs_rotate_sum={speed} rotate_sum_time={how}")


if __name__ == "__main__":
    main()
