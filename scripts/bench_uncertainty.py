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
    python scripts/bench_uncertainty.py --solver prior --meshes none --generated 2 --generated-first 2008

``--solver prior`` is ``solver=voxel_learned`` composed from ``conf/solver/`` as a job would
(:func:`dipnet.jobs.configured.configured`, as ``scripts/bench_quality.py``); its weights are for a
64^3 grid, which ``--n`` then defaults to (another ``--n`` is refused). ``--generated K`` adds the generated
shapes of seeds ``--generated-first`` .. + K - 1 (refused where the prior's weights were trained or validated),
``--mesh-files`` any mesh files (e.g. validation meshes that are not bundled); ``--meshes none``: no bundled mesh.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from dipnet.jobs.configured import check_test_seeds, configured
from dipnet.experiments.bench_options import check_run_options
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.evaluation.ensemble import (brier_score, check_ensemble_options, ensemble_maps, occupancy_probability,
                                        reliability, sample_ensemble)
from dipnet.evaluation.uncertainty import SURE_P_WRONG, calibration_by_decile, sure_error_rate, uncertainty
from dipnet.operators import make_operator
from dipnet.preprocessing.datasets import MESHES_DIR, check_mesh_names
from dipnet.shapes import ShapeError, load_mesh
from dipnet.shapes.procedural import generated_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers import SOLVERS as REGISTERED
from dipnet.solvers.denoiser import load_weights

METHODS = ("linearised", "samples", "samples_hard", "own")
#: ``--solver`` names and their factories (``factory(progress=..., seed=...)``); ``prior`` is the job's recipe.
SOLVERS = {**{name: REGISTERED[name] for name in ("voxel", "dip", "implicit", "minnorm")},
           "prior": configured("voxel_learned")}
#: Grid resolution per ``--solver`` when ``--n`` is not given; ``prior``: its weights' grid (:func:`default_n`).
DEFAULT_N = 32
#: The ``--meshes`` name that selects no bundled mesh (with ``--generated`` / ``--mesh-files``: those alone).
NO_MESH = "none"


def default_n(solver: str) -> int:
    """The ``--n`` a solver runs at by default: the learned prior's weights' grid for ``prior``, else ``DEFAULT_N``."""
    return int(load_weights(None)[1]["n"]) if solver == "prior" else DEFAULT_N


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", nargs="+", default=["bunny", "fish", "part_B13", "hollow_cube"],
                   help=f"bundled meshes; {NO_MESH}: none (with --generated or --mesh-files)")
    p.add_argument("--mesh-files", nargs="*", type=Path, default=[], help="further mesh files (any folder)")
    p.add_argument("--generated", type=int, default=0, help="number of generated test shapes")
    p.add_argument("--generated-first", type=int, default=2008, help="seed of the first generated test shape")
    p.add_argument("--n", type=int, default=None,
                   help=f"grid resolution N (default {DEFAULT_N}; --solver prior: its weights' grid, 64)")
    p.add_argument("--dips", type=int, default=41, help="Fibonacci-hemisphere dips")
    p.add_argument("--noise", nargs="+", default=["clean", "snr"], choices=["clean", "snr"])
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR (dB) for --noise snr")
    p.add_argument("--solver", default="voxel", choices=list(SOLVERS),
                   help="prior: solver=voxel_learned as a job composes it")
    p.add_argument("--samples", type=int, default=4, help="ensemble members")
    p.add_argument("--iterations-scale", type=float, default=1.0, help="share of the solver's iterations per member")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write every row to this JSON file")
    p.add_argument("--quick", action="store_true",
                   help="bunny and torus at 24^3 (--solver prior: 64^3), noise-free (about a minute idle)")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values; the prior keeps its weights' grid
        apply_quick(args, given_options(p, argv), meshes=["bunny", "torus"], noise=["clean"],
                    n=None if args.solver == "prior" else 24)
    if args.meshes == [NO_MESH]:
        args.meshes = []
    try:
        check_mesh_names(args.meshes)
    except FileNotFoundError as exc:  # now, not after the meshes before it
        p.error(f"--meshes: {exc}")
    missing = [str(path) for path in args.mesh_files if not path.is_file()]
    if missing:
        p.error(f"--mesh-files: no file {', '.join(missing)}")
    check_mesh_files_and_run_options(p, args)
    if args.generated:
        try:
            check_test_seeds(args.generated_first, args.generated)
        except ValueError as exc:
            p.error(str(exc))
    if not args.meshes and not args.mesh_files and not args.generated:
        p.error(f"no case: --meshes {NO_MESH} without --generated or --mesh-files")
    n = default_n(args.solver)
    if args.n is None:
        args.n = n
    elif args.solver == "prior" and args.n != n:  # now, not after the first case's simulation
        p.error(f"--solver prior: its weights are for a {n}^3 grid, not --n {args.n}")
    try:  # now, not by a traceback after the first case's reference solve
        Grid(args.n, 3)
        fibonacci_hemisphere(args.dips)
        check_ensemble_options(args.samples, args.iterations_scale)
    except ValueError as exc:
        p.error(f"--n {args.n}, --dips {args.dips}, --samples {args.samples}, --iterations-scale "
                f"{args.iterations_scale:g}: {exc}")
    return args


def check_mesh_files_and_run_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit through ``p.error`` on a ``--mesh-files`` file that is no mesh, or a run option no case could use
    (:func:`~dipnet.experiments.bench_options.check_run_options`): now, not by a traceback after the cases before
    (or, for ``--json``, after every case)."""
    for path in args.mesh_files:
        try:
            load_mesh(path)
        except ShapeError as exc:
            p.error(f"--mesh-files: {exc}")
    try:
        check_run_options(args)
    except ValueError as exc:
        p.error(str(exc))


def scores(probability: np.ndarray, p_wrong: np.ndarray, binary: np.ndarray, truth: np.ndarray) -> dict:
    """Deciles, Brier score, expected calibration error and the error rate where the method is sure
    (``sure``: ``p_wrong`` below ``SURE_P_WRONG``, a job's ``error_rate_where_sure``; NaN when no voxel is) of one
    method on one case."""
    deciles = calibration_by_decile(p_wrong, binary, truth)
    return {"deciles": [round(float(v), 4) for v in deciles], "top": float(deciles[-1]),
            "brier": brier_score(probability, binary, truth), "ece": reliability(probability, binary, truth)[3],
            "sure": sure_error_rate(p_wrong, binary, truth)[0]}


def cases(args) -> list[tuple[str, object]]:
    """``(label, source)`` per shape: bundled mesh names, ``--mesh-files`` paths and generated seeds, in that order."""
    return ([(name, MESHES_DIR / f"{name}.ply") for name in args.meshes]
            + [(path.stem, path) for path in args.mesh_files]
            + [(f"generated{seed}", seed) for seed in range(args.generated_first,
                                                            args.generated_first + args.generated)])


def make_shape(source: object, radius: float):
    """The shape of a case's ``source`` (a mesh path, or a generated shape's seed) whose farthest point is at ``radius``
    mm."""
    return generated_shape(source, radius=radius) if isinstance(source, int) else load_mesh(source, radius=radius)


def run_case(args, mesh: str, noise: str, source: object) -> list[dict]:
    """The rows of every method on the shape ``source`` (:func:`make_shape`) labelled ``mesh``, at ``noise``."""
    grid = Grid(args.n, 3)
    shape = make_shape(source, 0.9 * grid.radius)
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
              f"{row['sure']:7.4f} {seconds:7.1f}  {' '.join(f'{v:.3f}' for v in row['deciles'])}", flush=True)

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
    print(f"{'mesh':<12} {'noise':>5} {'method':<13} {'Brier':>7} {'ECE':>7} {'top':>6} {'sure':>7} {'time s':>7}  "
          "error rate per p_wrong decile (lowest first)")
    rows = [row for mesh, source in cases(args) for noise in args.noise for row in run_case(args, mesh, noise, source)]
    print(f"\nmeans over {len(rows) // len(METHODS)} cases\n{'method':<13} {'Brier':>7} {'ECE':>7} {'top':>6} "
          f"{'sure':>7} {'time s':>7}  deciles (sure: error rate where p_wrong < {SURE_P_WRONG:g})")
    means = {}
    for method in METHODS:
        items = [r for r in rows if r["method"] == method]
        means[method] = {k: statistics.fmean(r[k] for r in items) for k in ("brier", "ece", "top", "seconds")}
        means[method]["sure"] = float(np.nanmean([r["sure"] for r in items])) \
            if any(r["sure"] == r["sure"] for r in items) else float("nan")  # NaN: no sure voxel in any case
        deciles = np.mean([r["deciles"] for r in items], axis=0)
        print(f"{method:<13} {means[method]['brier']:7.4f} {means[method]['ece']:7.4f} {means[method]['top']:6.3f} "
              f"{means[method]['sure']:7.4f} {means[method]['seconds']:7.1f}  {' '.join(f'{v:.3f}' for v in deciles)}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print("RESULT " + " ".join(f"{key}_{method}={means[method][key]:.4f}" for key in ("brier", "ece", "top")
                               for method in ("samples", "linearised")))
    return rows


if __name__ == "__main__":
    main()
