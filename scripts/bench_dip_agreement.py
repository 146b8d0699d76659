"""Does the dip-agreement check find mislabelled dips and a moved object, and leave correct scans alone? Random cases.

:func:`~dipnet.preprocessing.dip_agreement.dip_agreement` (part of the consistency check a job records) fits the
central moments (orders 2-4) of every dip's profile with the polynomials one object gives and names the dips that
miss them beyond ``OUTLIER_SIGMAS`` of their noise and ``OUTLIER_SHARE`` of the object's scale. Random cases,
seeded by ``--seed``: ``--trials`` scans of each 3D shape of the pool (the 3D built-ins and the 16 bundled meshes,
45 mm in radius, in a random orientation), on ``n^3`` slabs with ``n`` 24 or 48, 12-123 dips on the Fibonacci
hemisphere (or, one scan in three, the authors' rig's 0-35 deg plan), noise-free one time in five, else an SNR
uniform in 5-40 dB. Each correct scan (``ok``) is then broken four ways: two dips filed under each other's direction
(``swap``), the orientation log one dip off from the middle on (``off_by_one``), and the object turned by 20 or
45 deg about a random axis halfway through the scan (``slip20``, ``slip45``). The table gives, per kind, the share
of scans with an outlier at the shipped limits and at others (false alarms for ``ok``, detections for the rest; the
dips set aside before the final fit are chosen at the shipped limits, so the other rows are close, not exact),
the shipped limits' rates per SNR band, and the ``ok`` scans nearest the limits. The authors' real recording
(``dipnet/data/real``, as ``experiment=cats_real`` reads it) is scored too. Last line ``RESULT false_alarms=<>
detected_swap=<> detected_off_by_one=<> detected_slip20=<> detected_slip45=<> cats_outliers=<> cases=<>``.

    python scripts/bench_dip_agreement.py            # 4 scans per shape (80 cases, 400 scored scans)
    python scripts/bench_dip_agreement.py --quick    # 1 scan of 8 shapes
"""

from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from dipnet.core.framing import extent_around
from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.experiments.prior_pairs import plan_directions
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.shape_pool import (add_pool_options, check_pool_options, shape_makers, shape_names,
                                           start_pool_run)
from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.preprocessing.dip_agreement import OUTLIER_SHARE, OUTLIER_SIGMAS, dip_scores
from dipnet.preprocessing.sources import read_recorded
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.jobs.cli import user_errors

RADIUS_MM, FILL = 45.0, 0.9
DIPS, RESOLUTIONS, RIG_SHARE, RIG_TILT_DEG = (12, 123), (24, 48), 1 / 3, 35.0
SNR_DB, NOISE_FREE_SHARE = (5.0, 40.0), 0.2
SLIPS_DEG = (20.0, 45.0)
BANDS = (("noise-free", None, None), ("30-40 dB", 30.0, 40.01), ("15-30 dB", 15.0, 30.0), ("5-15 dB", 5.0, 15.0))
KINDS = ("ok", "swap", "off_by_one", "slip20", "slip45")
#: Other limits the table shows: (sigmas, share)
LIMITS = ((OUTLIER_SIGMAS, OUTLIER_SHARE), (5.0, 0.05), (12.0, 0.05), (8.0, 0.03), (8.0, 0.1))
QUICK_SHAPES = ["ball_3d", "torus_3d", "chamber_box_3d", "bunny", "hammer", "fish", "spot", "wingnut"]
#: ``experiment=cats_real``'s reader options (conf/experiment/cats_real.yaml)
CATS = {"cross_section_mm2": 183600.0, "t_start": "geometry", "truncated": "keep", "smooth": True,
        "geometry": {"pivot_mm": 188.0, "tilt_axis_offset_mm": -18.0}}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_pool_options(p, trials=4, resolution=0, shapes_help="3D shapes to dip (default: all; e.g. ball_3d bunny)",
                     resolution_help="slabs per dip (0: 24 or 48 at random)")
    p.add_argument("--quick", action="store_true", help=f"1 scan of {len(QUICK_SHAPES)} shapes")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), trials=1, shapes=QUICK_SHAPES)
    check_pool_options(p, args)
    return args


def sample_case(rng: np.random.Generator, name: str, resolution: int) -> dict:
    """One random scan of shape ``name`` and its faults' draws."""
    dips = int(rng.integers(DIPS[0], DIPS[1] + 1))
    return {"shape": name, "n": resolution or int(rng.choice(RESOLUTIONS)), "dips": dips,
            "rig": bool(rng.random() < RIG_SHARE), "snr_db": None if rng.random() < NOISE_FREE_SHARE else
            float(rng.uniform(*SNR_DB)), "seed": int(rng.integers(1 << 30)),
            "rotation": Rotation.random(random_state=int(rng.integers(1 << 30))).as_quat().tolist(),
            "swap": sorted(int(i) for i in rng.choice(dips, 2, replace=False)),
            "slip_axis": Rotation.random(random_state=int(rng.integers(1 << 30))).as_rotvec().tolist()}


def scored(measurement) -> dict:
    """The largest outlier scores of a measurement and whether each limit of :data:`LIMITS` flags it."""
    scores = dip_scores(measurement)
    if scores is None:
        return {"tested": 0, "flags": [False] * len(LIMITS), "share": float("nan"), "sigmas": float("nan")}
    worst = int(np.argmax(np.minimum(scores.share / OUTLIER_SHARE, scores.sigmas / OUTLIER_SIGMAS)))
    return {"tested": len(scores.index),
            "flags": [bool(scores.outliers(share, sigmas).any()) for sigmas, share in LIMITS],
            "share": float(scores.share[worst]), "sigmas": float(scores.sigmas[worst])}


def run_case(case: dict, makers: dict) -> list[dict]:
    """Simulate a correct scan and its faults; one scored row per kind."""
    shape = makers[case["shape"]][1](RADIUS_MM)
    grid = Grid(case["n"], 3, extent_around(shape.radius(), case["n"], FILL))
    plan = plan_directions(case["dips"], RIG_TILT_DEG) if case["rig"] else fibonacci_hemisphere(case["dips"])
    turn = torch.as_tensor(Rotation.from_quat(case["rotation"]).as_matrix())
    true = torch.as_tensor(plan, dtype=torch.float64) @ turn.T  # the plan's directions in the object's frame

    def dip(directions):
        sensor = LevelSensor(snr_db=case["snr_db"], seed=case["seed"])
        return simulate_measurement(shape, directions, grid=grid, sensor=sensor, seed=case["seed"], progress=False)[1]

    ok = dip(true)
    filed = ok.directions
    swapped = filed.clone()
    swapped[case["swap"]] = filed[case["swap"][::-1]]
    half = case["dips"] // 2
    shifted = torch.cat([filed[:half], filed[half + 1:], filed[half:half + 1]])
    rows = [("ok", ok), ("swap", replace(ok, directions=swapped)), ("off_by_one", replace(ok, directions=shifted))]
    for angle in SLIPS_DEG:
        axis = np.asarray(case["slip_axis"]) / np.linalg.norm(case["slip_axis"])
        slip = torch.as_tensor(Rotation.from_rotvec(np.radians(angle) * axis).as_matrix())
        moved = torch.cat([true[:half], true[half:] @ slip.T])
        rows.append((f"slip{angle:.0f}", replace(dip(moved), directions=filed)))
    return [{**case, "kind": kind, **scored(measurement)} for kind, measurement in rows]


def cats_row() -> dict:
    """The authors' real recording, read as ``experiment=cats_real`` reads it (40 slabs over 360 mm)."""
    return {"shape": "cats (real)", **scored(read_recorded(str(CATS_CSV), Grid(40, 3, 360.0), **CATS))}


def print_table(rows: list[dict], cats: dict) -> None:
    """Flag rates per kind and limits, the correct scans' largest scores and the RESULT line."""
    print(f"\n{len([r for r in rows if r['kind'] == 'ok'])} correct scans and their faults; "
          "share of scans with an outlier")
    print(f"{'limits (sigmas, share)':24s}" + "".join(f"{k:>12s}" for k in KINDS))
    for j, (sigmas, share) in enumerate(LIMITS):
        rates = [np.mean([r["flags"][j] for r in rows if r["kind"] == kind]) for kind in KINDS]
        mark = " (shipped)" if j == 0 else ""
        print(f"{f'{sigmas:g}, {share:g}{mark}':24s}" + "".join(f"{v:12.3f}" for v in rates))
    print("\nat the shipped limits, per SNR band (scans)")
    print(f"{'band':24s}" + "".join(f"{k:>12s}" for k in KINDS))
    for name, low, high in BANDS:
        inside = [r for r in rows if (r["snr_db"] is None if low is None else
                                      r["snr_db"] is not None and low <= r["snr_db"] < high)]
        rates = [np.mean([r["flags"][0] for r in inside if r["kind"] == kind]) if inside else float("nan")
                 for kind in KINDS]
        print(f"{f'{name} ({len(inside) // len(KINDS)})':24s}" + "".join(f"{v:12.3f}" for v in rates))
    ok = sorted((r for r in rows if r["kind"] == "ok"), key=lambda r: -min(r["share"] / OUTLIER_SHARE,
                                                                          r["sigmas"] / OUTLIER_SIGMAS))
    print("\ncorrect scans nearest the limits (share, sigmas):")
    for r in ok[:5]:
        print(f"  {r['shape']:16s} n={r['n']} dips={r['dips']:3d} rig={r['rig']!s:5s} snr={r['snr_db']}: "
              f"{r['share']:.4f}, {r['sigmas']:.1f}")
    print(f"cats (real), {cats['tested']} whole dips: {cats['share']:.4f}, {cats['sigmas']:.1f}, "
          f"outliers: {cats['flags'][0]}")
    rates = {kind: np.mean([r["flags"][0] for r in rows if r["kind"] == kind]) for kind in KINDS}
    print(f"RESULT false_alarms={rates['ok']:.3f} detected_swap={rates['swap']:.3f} "
          f"detected_off_by_one={rates['off_by_one']:.3f} detected_slip20={rates['slip20']:.3f} "
          f"detected_slip45={rates['slip45']:.3f} cats_outliers={int(cats['flags'][0])} "
          f"cases={len(rows) // len(KINDS)}")


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> list[dict]:
    """Run the benchmark; returns one row per scored scan."""
    args = parse_args(argv)
    names = shape_names(args.shapes, ndim=3)
    rng = start_pool_run(args)
    makers = shape_makers()
    cases = [sample_case(rng, name, args.resolution) for _ in range(args.trials) for name in names]
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for case in tqdm(cases, desc="cases"):
            rows.extend(run_case(case, makers))
        cats = cats_row()
    print_table(rows, cats)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
