"""Air pockets and vessels: how much they change the dips and the results, and whether the check names them.

The dip transform assumes water reaches every cavity of the object as soon as the water line passes it. A cavity
that opens downward keeps its air instead, and one that opens upward stays dry until the water reaches its rim
(:mod:`dipnet.simulator.pockets`). Random cases, seeded by ``--seed``: ``--trials`` scans of each shape of the 3D
pool (:mod:`dipnet.experiments.shape_pool`: the built-ins and the 16 bundled meshes, 45 mm in radius), each along
20-60 random directions over the whole sphere (a rig may hold an object any way up), noise-free one time in five,
else 20-40 dB that the sensor states. Each scan is simulated twice with the same noise, as the dip transform assumes
and with the simulator's pockets (``Pockets()``: 64 cells per axis), and both are solved by the job's default solver
(``solver=voxel`` of ``conf/config.yaml``, via Hydra's compose) on a 32^3 grid around the object
(``--resolution``) and checked as the job checks them.

Per shape the table gives the dips' pocket and vessel volumes over the object's (mean and largest over the dips),
the vessel dips (a vessel over :data:`~dipnet.evaluation.consistency.LEVEL_DROP_TOL` of the volume) in which
preprocessing found the level falling (``level_drop``), the dips without a vessel (under 0.1 %) in which it did
(false falls), the IoU of both results against the truth, and the verdicts with pockets (``named``: the check names a
flooding cavity). A case is **affected** when the pockets cost its result more than ``AFFECTED_IOU`` of IoU, and
**silent** when it is affected and still ``consistent``. Last line ``RESULT affected=<> silent=<>
vessel_dips_detected=<> false_falls=<> cases=<>``.

    python scripts/bench_pockets.py --threads 1            # 20 shapes, 1 scan each
    python scripts/bench_pockets.py --quick                # 4 shapes at 24^3, 20-30 dips
    python scripts/bench_pockets.py --shapes chamber_box_3d boot --trials 3 --json rows.json
"""

from __future__ import annotations

import argparse
import json
import logging
import warnings

import numpy as np
import torch
from hydra.utils import instantiate
from tqdm.auto import tqdm

from dipnet.core.framing import extent_around
from dipnet.core.grid import Grid
from dipnet.evaluation.consistency import LEVEL_DROP_TOL, check_consistency
from dipnet.evaluation.metrics import iou, reference_level
from dipnet.experiments.bench_options import count_type
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.shape_pool import add_pool_options, check_pool_options, shape_makers, shape_names
from dipnet.jobs.tuning import compose_job
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.pockets import Pockets
from dipnet.simulator.simulate import simulate_measurement
from dipnet.jobs.cli import user_errors

RADIUS_MM, FILL = 45.0, 0.9
DIPS = (20, 60)
SNR_DB, NOISE_FREE_SHARE = (20.0, 40.0), 0.2
AFFECTED_IOU = 0.02
NO_VESSEL = 0.001  # a dip whose vessels hold less than this share of the volume: a level drop there is a false fall
QUICK_SHAPES = ["chamber_box_3d", "boot", "bunny", "hollow_cube"]
JOB = ["solver=voxel", "output.progress=false"]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_pool_options(p, trials=1, resolution=32, shapes_help="the 3D shapes to dip (default: all; e.g. chamber_box_3d "
                     "boot)", json_help="also write every case's row to this JSON file")
    p.add_argument("--dips", type=count_type(1, "dips"), nargs=2, default=list(DIPS), metavar=("LOW", "HIGH"),
                   help="the range of the number of dips")
    p.add_argument("--quick", action="store_true", help=f"{len(QUICK_SHAPES)} shapes at 24^3, 20-30 dips")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), shapes=QUICK_SHAPES, resolution=24, dips=[20, 30])
    check_pool_options(p, args)
    if args.dips[0] > args.dips[1]:  # was numpy's "low > high" traceback at the first case
        p.error(f"--dips LOW HIGH: LOW must not be above HIGH, got {args.dips[0]} {args.dips[1]}")
    return args


def sample_case(rng: np.random.Generator, name: str, dips: tuple[int, int]) -> dict:
    """One random scan of shape ``name``: its directions ``(D, 3)`` (uniform on the sphere), SNR (``None``:
    noise-free) and noise seed."""
    n_dips = int(rng.integers(dips[0], dips[1] + 1))
    directions = rng.normal(size=(n_dips, 3))
    snr = None if rng.random() < NOISE_FREE_SHARE else float(rng.uniform(*SNR_DB))
    return {"shape": name, "dips": n_dips, "snr_db": snr, "noise_seed": int(rng.integers(1 << 30)),
            "directions": (directions / np.linalg.norm(directions, axis=1, keepdims=True)).tolist()}


def run_case(case: dict, cfg, resolution: int) -> dict:
    """Simulate one case without and with pockets, solve and check both; the case's row."""
    shape = shape_makers()[case["shape"]][1](RADIUS_MM)
    grid = Grid(resolution, 3, extent_around(shape.radius(), resolution, FILL))
    truth_occupancy = shape.occupancy(grid, supersample=3).numpy()
    truth = truth_occupancy > reference_level(truth_occupancy, grid, shape.volume)
    row = {k: v for k, v in case.items() if k != "directions"}
    for label, pockets in (("plain", None), ("pockets", Pockets())):
        raw, measurement = simulate_measurement(shape, np.asarray(case["directions"]), grid=grid,
                                                sensor=LevelSensor(snr_db=case["snr_db"], seed=case["noise_seed"]),
                                                seed=case["noise_seed"], pockets=pockets, progress=False)
        operator = instantiate(cfg.operator)(grid, measurement.directions, grid.n)
        recon = instantiate(cfg.solver, seed=case["noise_seed"]).solve(measurement, operator)
        checked = check_consistency(measurement, operator, recon, warn=False)
        row[f"iou_{label}"] = iou(recon.binary, truth)
        row[f"verdict_{label}"] = checked.verdict
        if pockets is not None:
            row["pocket_share"] = [o.meta["pocket_mm3"] / shape.volume for o in raw.orientations]
            row["vessel_share"] = [o.meta["vessel_mm3"] / shape.volume for o in raw.orientations]
            row["drop_share"] = [drop / shape.volume for drop, _ in measurement.metadata["level_drop"]]
            row["named"] = any("level falling while the object went down" in w for w in checked.warnings)
    row["affected"] = row["iou_plain"] - row["iou_pockets"] > AFFECTED_IOU
    row["silent"] = row["affected"] and row["verdict_pockets"] == "consistent"
    return row


def dip_counts(row: dict) -> tuple[int, int, int, int]:
    """``(vessel dips, of them with a level drop, dips without a vessel, of them with a drop)`` of one case."""
    vessel, drop = np.asarray(row["vessel_share"]), np.asarray(row["drop_share"]) > 0
    big, none = vessel > LEVEL_DROP_TOL, vessel < NO_VESSEL
    return int(big.sum()), int((big & drop).sum()), int(none.sum()), int((none & drop).sum())


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> list[dict]:
    """Run the benchmark; returns one row per case."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.getLogger("dipnet").setLevel(logging.ERROR)
    rng = np.random.default_rng(args.seed)
    names = shape_names(args.shapes, ndim=3)
    cases = [sample_case(rng, name, tuple(args.dips)) for _ in range(args.trials) for name in names]
    cfg = compose_job(JOB)
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for case in tqdm(cases, desc="cases"):
            rows.append(run_case(case, cfg, args.resolution))
    print_table(rows, args)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


def print_table(rows: list[dict], args: argparse.Namespace) -> None:
    """One line per case and the ``RESULT`` line."""
    print(f"\n{args.trials} random scan(s) per shape (seed {args.seed}), {len(rows)} cases at {args.resolution}^3, "
          f"{args.dips[0]}-{args.dips[1]} dips over the sphere; solver=voxel. Shares of the object's volume; vessel "
          f"dips: over {LEVEL_DROP_TOL:.0%}; false falls: a level drop in a dip whose vessels hold under "
          f"{NO_VESSEL:.1%}\n")
    print("| shape | dips | SNR dB | pocket mean | pocket max | vessel mean | vessel max | vessel dips with a drop | "
          "false falls | IoU plain | IoU pockets | verdict plain | verdict pockets | named |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    totals = np.zeros(4, dtype=int)
    for r in rows:
        counts = dip_counts(r)
        totals += counts
        snr = "-" if r["snr_db"] is None else f"{r['snr_db']:.0f}"
        print(f"| {r['shape']} | {r['dips']} | {snr} | {np.mean(r['pocket_share']):.2%} | {max(r['pocket_share']):.2%} "
              f"| {np.mean(r['vessel_share']):.2%} | {max(r['vessel_share']):.2%} | {counts[1]}/{counts[0]} | "
              f"{counts[3]}/{counts[2]} | {r['iou_plain']:.3f} | {r['iou_pockets']:.3f} | {r['verdict_plain']} | "
              f"{r['verdict_pockets']} | {'yes' if r['named'] else 'no'} |")
    affected = [r for r in rows if r["affected"]]
    silent = [r["shape"] for r in affected if r["silent"]]
    detected = totals[1] / totals[0] if totals[0] else float("nan")
    print(f"\naffected (IoU lower by more than {AFFECTED_IOU:g} with pockets): {len(affected)} of {len(rows)} "
          f"({', '.join(r['shape'] for r in affected) or 'none'}); of them consistent: {len(silent)} "
          f"({', '.join(silent) or 'none'}); vessel dips with a level drop: {totals[1]}/{totals[0]}; false falls: "
          f"{totals[3]}/{totals[2]}")
    print(f"RESULT affected={len(affected)} silent={len(silent)} vessel_dips_detected={detected:.3f} "
          f"false_falls={totals[3]} cases={len(rows)}")


if __name__ == "__main__":
    main()
