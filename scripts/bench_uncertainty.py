"""Calibration of the per-voxel uncertainty: the ensemble (``output.uncertainty=samples``) against the
linearised posterior (``output.uncertainty=true``) on bundled meshes (not a timed test).

For every mesh, noise level and the Fibonacci plan of ``--dips`` dips on an ``--n``^3 grid, the
solver reconstructs once (the reference) and each method turns its uncertainty into an occupancy
probability ``p`` and the probability ``p_wrong`` that each of the reference's binary calls is wrong:

* ``linearised``: :func:`dipnet.evaluation.uncertainty.uncertainty` (``p = 1 - p_wrong`` inside);
* ``samples``: :func:`dipnet.evaluation.ensemble.sample_ensemble` with ``--samples`` members, the mean of
  their threshold-centred occupancies (``soft``);
* ``samples_hard``: the same members, the share of them that call the voxel occupied;
* ``own``: no uncertainty method, the reference's own threshold-centred occupancy as ``p`` (what a
  method must beat to be worth its cost).

Scores over the support (the reference dilated by two voxels, and the true object): the error rate per
``p_wrong`` decile (lowest first; a calibrated ranking rises), the Brier score of ``p`` and the expected
calibration error (10 equal-width bins). Prints a row per case and method, the means per method, and

    RESULT brier_samples=<> brier_linearised=<> ece_samples=<> ece_linearised=<> top_samples=<> top_linearised=<>

(means over the cases; ``top_*``: error rate of the most uncertain decile).

    python scripts/bench_uncertainty.py --threads 1                      # 4 meshes, 32^3, clean and 30 dB
    python scripts/bench_uncertainty.py --quick                          # 2 meshes, 24^3, clean
    python scripts/bench_uncertainty.py --meshes bunny --n 48 --samples 8
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.evaluation.ensemble import (brier_score, check_ensemble_options, ensemble_maps, occupancy_probability,
                                        reliability, sample_ensemble)
from dipnet.evaluation.uncertainty import calibration_by_decile, uncertainty
from dipnet.operators import make_operator
from dipnet.preprocessing.datasets import MESHES_DIR, check_mesh_names
from dipnet.shapes import load_mesh
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers import SOLVERS

METHODS = ("linearised", "samples", "samples_hard", "own")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", nargs="+", default=["bunny", "fish", "part_B13", "hollow_cube"])
    p.add_argument("--n", type=int, default=32, help="grid resolution N")
    p.add_argument("--dips", type=int, default=41, help="Fibonacci-hemisphere dips")
    p.add_argument("--noise", nargs="+", default=["clean", "snr"], choices=["clean", "snr"])
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR (dB) for --noise snr")
    p.add_argument("--solver", default="voxel", choices=["voxel", "dip", "implicit", "minnorm"])
    p.add_argument("--samples", type=int, default=4, help="ensemble members")
    p.add_argument("--iterations-scale", type=float, default=1.0, help="share of the solver's iterations per member")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write every row to this JSON file")
    p.add_argument("--quick", action="store_true", help="bunny and torus at 24^3, noise-free (about a minute idle)")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), meshes=["bunny", "torus"], n=24, noise=["clean"])
    try:
        check_mesh_names(args.meshes)
    except FileNotFoundError as exc:  # now, not after the meshes before it
        p.error(f"--meshes: {exc}")
    try:  # now, not by a traceback after the first case's reference solve
        Grid(args.n, 3)
        fibonacci_hemisphere(args.dips)
        check_ensemble_options(args.samples, args.iterations_scale)
    except ValueError as exc:
        p.error(f"--n {args.n}, --dips {args.dips}, --samples {args.samples}, --iterations-scale "
                f"{args.iterations_scale:g}: {exc}")
    return args


def scores(probability: np.ndarray, p_wrong: np.ndarray, binary: np.ndarray, truth: np.ndarray) -> dict:
    """Deciles, Brier score and expected calibration error of one method on one case."""
    deciles = calibration_by_decile(p_wrong, binary, truth)
    return {"deciles": [round(float(v), 4) for v in deciles], "top": float(deciles[-1]),
            "brier": brier_score(probability, binary, truth), "ece": reliability(probability, binary, truth)[3]}


def run_case(args, mesh: str, noise: str) -> list[dict]:
    grid = Grid(args.n, 3)
    shape = load_mesh(MESHES_DIR / f"{mesh}.ply", radius=0.9 * grid.radius)
    sensor = LevelSensor(snr_db=args.snr if noise == "snr" else None, quantum_mm=0.0, seed=args.seed)
    _, measurement = simulate_measurement(shape, fibonacci_hemisphere(args.dips), grid=grid, sensor=sensor,
                                          seed=args.seed, progress=False)
    truth = shape.occupancy(grid, supersample=3).numpy() >= 0.5
    operator = make_operator(grid, measurement.directions, grid.n)
    solver = SOLVERS[args.solver](progress=False, seed=args.seed)
    t0 = time.perf_counter()
    recon = solver.solve(measurement, operator)
    solve_seconds = time.perf_counter() - t0
    binary = recon.binary
    rows = []

    def add(method: str, probability: np.ndarray, p_wrong: np.ndarray, seconds: float) -> None:
        row = {"mesh": mesh, "noise": noise, "method": method, "seconds": seconds, "solve_seconds": solve_seconds,
               "errors": int((binary != truth).sum()), **scores(probability, p_wrong, binary, truth)}
        rows.append(row)
        print(f"{mesh:<12} {noise:>5} {method:<13} {row['brier']:7.4f} {row['ece']:7.4f} {row['top']:6.3f} "
              f"{seconds:7.1f}  {' '.join(f'{v:.3f}' for v in row['deciles'])}", flush=True)

    t0 = time.perf_counter()
    maps, _ = uncertainty(recon, measurement, operator)
    add("linearised", occupancy_probability(maps["p_wrong"], binary), maps["p_wrong"], time.perf_counter() - t0)
    ensemble = sample_ensemble(solver, recon, measurement, operator, n_samples=args.samples, seed=args.seed,
                               iterations_scale=args.iterations_scale)
    for method, soft in (("samples", True), ("samples_hard", False)):
        maps = ensemble_maps(recon, ensemble, soft)
        add(method, maps["probability"], maps["p_wrong"], ensemble.seconds)
    own = np.clip(recon.occupancy.double().numpy() - recon.threshold + 0.5, 0.0, 1.0)
    add("own", own, np.where(binary, 1.0 - own, own), 0.0)
    return rows


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"{args.solver}, {args.dips} dips, {args.n}^3, {args.samples} members x {args.iterations_scale} iterations")
    print(f"{'mesh':<12} {'noise':>5} {'method':<13} {'Brier':>7} {'ECE':>7} {'top':>6} {'time s':>7}  "
          "error rate per p_wrong decile (lowest first)")
    rows = [row for mesh in args.meshes for noise in args.noise for row in run_case(args, mesh, noise)]
    print(f"\nmeans over {len(rows) // len(METHODS)} cases\n{'method':<13} {'Brier':>7} {'ECE':>7} {'top':>6} "
          f"{'time s':>7}  deciles")
    means = {}
    for method in METHODS:
        items = [r for r in rows if r["method"] == method]
        means[method] = {k: statistics.fmean(r[k] for r in items) for k in ("brier", "ece", "top", "seconds")}
        deciles = np.mean([r["deciles"] for r in items], axis=0)
        print(f"{method:<13} {means[method]['brier']:7.4f} {means[method]['ece']:7.4f} {means[method]['top']:6.3f} "
              f"{means[method]['seconds']:7.1f}  {' '.join(f'{v:.3f}' for v in deciles)}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print("RESULT " + " ".join(f"{key}_{method}={means[method][key]:.4f}" for key in ("brier", "ece", "top")
                               for method in ("samples", "linearised")))
    return rows


if __name__ == "__main__":
    main()
