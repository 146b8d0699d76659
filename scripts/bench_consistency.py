"""How often does the consistency check's residual rule flag a correct result, and how often a wrong one? Random cases.

:func:`~dipnet.evaluation.consistency.check_consistency` calls a result ``inconsistent`` when (among other checks)
the relative profile residual of its binary shape exceeds its limit
(:func:`~dipnet.evaluation.consistency.allowed_residual`): ``hypot(f * expected, floor_n)``, ``expected`` being what
the noise explains (``||sigma|| / ||g||`` with the noise the measurement states, as a simulated
:class:`~dipnet.simulator.physics.LevelSensor` with an SNR does, else estimated: the smaller of the profiles' own
estimate and ``sqrt(2)`` times the readings' noise, :func:`~dipnet.evaluation.consistency.estimated_slab_noise`),
``f`` 1.25 for a stated noise and 3 for an estimated one, ``floor_n = max(0.05, 3 / n)`` on ``n`` voxels per axis.
Before commit 6f0ebf7 an unstated noise was estimated from the profiles alone (``profiles``); before 2026-11-29
the rule was ``max(3 * expected, 0.05)`` (``before``). This benchmark measures the rule's false alarms and misses, and
those of other rules.

Random cases, seeded by ``--seed``: ``--trials`` scans per shape of the 3D built-ins (ball, box, torus, chamber box),
the 16 bundled meshes and the 2D built-ins (disk, chamber box, elephant), 45 mm in radius on the job's grid around
the object (``fill`` 0.9; 24^3 in 3D, 48^2 in 2D, or ``--resolution``), with a random number of dips (3D 20-80
on the Fibonacci hemisphere, 2D 10-40 equal angles) and a random noise: noise-free one time in five (the noise then
estimated), else an SNR uniform in 5-40 dB that the sensor states. Each scan is solved by the job's default optimisation
solver (``solver=voxel`` of ``conf/config.yaml`` and its ``operator``, via Hydra's compose) and checked as the job
checks it. Then WRONG candidates are checked against the same measurement with the same operator: (a) a ball of
the reconstruction's volume at the data's centroid, (b) the reconstruction shifted by 2 voxels along a random axis
(either way), (c) another shape of the pool (same dimension) scaled to the reconstruction's volume, centred on the
data's centroid. Every candidate and every reconstruction is scored by IoU against the truth (its voxels above
:func:`~dipnet.evaluation.metrics.reference_level`, as the job scores it). The truth's own voxels are checked too
(what the grid alone leaves in the residual: the hammer's thin handle does not fit 24^3).

A reconstruction with IoU >= 0.85 is **correct**: flagging it is a false alarm. A candidate (or a reconstruction)
with IoU < 0.8 is **wrong**: flagging it is a detection (the ones in between count as neither). Per SNR band
(noise-free, 30-40, 15-30, 5-15 dB) the table gives the quantiles of residual / expected of the correct results,
their share the current rule flags (the residual check alone, and the whole verdict), the wrong candidates'
residual / expected, and, for the current rule, the rules before (``profiles``, ``before``) and other rules:
``max(f * expected, 0.05)`` (``fN``, f in 1.25, 1.5, 2) and ``hypot(f * expected, floor_n)`` (``hypotN``, f in 1.25,
1.5, 2, 3), the share of correct results flagged (false alarms) and of wrong candidates flagged (detected). Last line
``RESULT false_alarms_current=<> detected_current=<> false_alarms_before=<> detected_before=<> ... cases=<>`` (over
all bands).

    python scripts/bench_consistency.py --threads 1     # 10 scans per shape (230 cases)
    python scripts/bench_consistency.py --quick         # 2 scans of 8 shapes (16 cases)
    python scripts/bench_consistency.py --shapes ball_3d bunny --trials 4 --json rows.json   # some shapes, the rows
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
import warnings

import numpy as np
import torch
from hydra.utils import instantiate
from tqdm.auto import tqdm

from dipnet.core.framing import extent_around
from dipnet.core.grid import Grid
from dipnet.core.measurement import estimate_slab_sigma
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.consistency import RESIDUAL_FLOOR, RESIDUAL_FLOOR_VOXELS, allowed_residual, check_consistency
from dipnet.evaluation.metrics import iou, reference_level
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.shape_pool import (add_pool_options, check_pool_options, shape_makers, shape_names,
                                           start_pool_run)
from dipnet.jobs.tuning import compose_job
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.base import measured_profiles
from dipnet.jobs.cli import user_errors

RADIUS_MM, FILL = 45.0, 0.9
DIPS = {2: (10, 40), 3: (20, 80)}
SNR_DB, NOISE_FREE_SHARE = (5.0, 40.0), 0.2
CORRECT_IOU, WRONG_IOU = 0.85, 0.8
CANDIDATES = ("ball", "shifted", "other")
SHIFT_VOXELS = 2
FACTORS = (1.25, 1.5, 2.0, 3.0)
BANDS = (("noise-free", None, None), ("30-40 dB", 30.0, 40.01), ("15-30 dB", 15.0, 30.0), ("5-15 dB", 5.0, 15.0))
QUICK_SHAPES = ["ball_3d", "torus_3d", "chamber_box_3d", "bunny", "hammer", "fish", "disk_2d", "elephant_2d"]
JOB = ["solver=voxel", "output.progress=false"]


def rules() -> dict[str, Callable[[dict], float]]:
    """The residual rules compared, by name: the limit above which each flags a row. ``current``: the check's own
    (``row["limit"]``: :func:`~dipnet.evaluation.consistency.allowed_residual`); ``profiles``: the same with an
    unstated noise estimated from the profiles alone (the rule before commit 6f0ebf7, which bounds that estimate by
    the readings' noise); ``before``: ``max(3 e, 0.05)`` with it, the rule before 2026-11-29; ``fX``: ``max(X e,
    0.05)``; ``hypotX``: ``hypot(X e, floor_n)`` with the grid's floor (the check's limit with one factor for both
    noise sources)."""
    out: dict[str, Callable[[dict], float]] = {
        "current": lambda r: r["limit"],
        "profiles": lambda r: allowed_residual(_profiles_expected(r), r["n"], r["noise_source"] == "sigma"),
        "before": lambda r: max(3.0 * _profiles_expected(r), RESIDUAL_FLOOR)}
    out.update({f"f{f:g}": (lambda r, f=f: max(f * r["expected"], RESIDUAL_FLOOR)) for f in FACTORS if f != 3.0})
    out.update({f"hypot{f:g}": (lambda r, f=f: allowed_residual(r["expected"], r["n"], True, factor=f))
                for f in FACTORS})
    return out


def _profiles_expected(row: dict) -> float:
    """What the noise explains in ``row`` as the check took it before commit 6f0ebf7: the stated noise, else the noise
    estimated from the profiles alone."""
    return row["expected"] if row["noise_source"] == "sigma" else row["expected_profiles"]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_pool_options(p, trials=10, resolution=24, shapes_help="the shapes to dip (default: all; names as in the rows, "
                     "e.g. ball_3d elephant_2d bunny)", resolution_help="voxels per axis of the 3D grid (2D: twice as "
                     "many pixels)", json_help="also write every checked result's row to this JSON file")
    p.add_argument("--quick", action="store_true", help=f"2 scans of {len(QUICK_SHAPES)} shapes")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), trials=2, shapes=QUICK_SHAPES)
    check_pool_options(p, args)
    return args


def sample_case(rng: np.random.Generator, name: str, ndim: int, pool: list[str]) -> dict:
    """One random scan of shape ``name``: dips, SNR (``None``: noise-free), noise seed, the shifted axis and
    direction, and the other shape of ``pool`` (``name`` itself when the pool holds no other)."""
    low, high = DIPS[ndim]
    n_dips = int(rng.integers(low, high + 1))
    snr = None if rng.random() < NOISE_FREE_SHARE else float(rng.uniform(*SNR_DB))
    others = [other for other in pool if other != name] or [name]
    return {"shape": name, "ndim": ndim, "dips": n_dips, "snr_db": snr, "noise_seed": int(rng.integers(1 << 30)),
            "shift_axis": int(rng.integers(ndim)), "shift_sign": int(rng.choice([-1, 1])),
            "other": others[int(rng.integers(len(others)))]}


def data_centroid(measurement, operator) -> np.ndarray:
    """The object's centroid ``(ndim,)`` (mm, ``x, y[, z]``) the dips give: each profile's centroid along its
    direction is ``c . theta``, fitted by least squares."""
    profiles = measured_profiles(measurement, operator).double().numpy()
    edges = operator.slab_edges().double().numpy()
    centres = 0.5 * (edges[1:] + edges[:-1])
    totals = profiles.sum(1)
    keep = totals > 0
    along = (profiles[keep] * centres).sum(1) / totals[keep]
    c, *_ = np.linalg.lstsq(operator.directions.double().numpy()[keep], along, rcond=None)
    return c


def ball_candidate(grid: Grid, voxels: int, centre: np.ndarray) -> np.ndarray:
    """The ``voxels`` voxels nearest to ``centre`` (mm): a ball of that volume, boolean ``grid.shape``."""
    distance = (grid.centers().numpy() - centre).reshape(-1, grid.ndim)
    return _top(-np.linalg.norm(distance, axis=1), voxels).reshape(grid.shape)


def shifted(binary: np.ndarray, axis: int, voxels: int) -> np.ndarray:
    """``binary`` moved by ``voxels`` along the array's ``axis`` (what leaves the grid is lost, 0 comes in)."""
    out = np.zeros_like(binary)
    src = [slice(None)] * binary.ndim
    dst = [slice(None)] * binary.ndim
    if voxels >= 0:
        src[axis], dst[axis] = slice(0, binary.shape[axis] - voxels), slice(voxels, None)
    else:
        src[axis], dst[axis] = slice(-voxels, None), slice(0, binary.shape[axis] + voxels)
    out[tuple(dst)] = binary[tuple(src)]
    return out


def other_shape_candidate(make, grid: Grid, voxels: int, centre: np.ndarray) -> np.ndarray:
    """Another shape (``make(radius)``) scaled to ``voxels`` voxels and moved (whole voxels) to ``centre`` (mm)."""
    probe = make(RADIUS_MM)
    volume = voxels * grid.voxel_volume
    shape = make(RADIUS_MM * (volume / probe.volume) ** (1.0 / grid.ndim))
    occupancy = shape.occupancy(grid, supersample=2).numpy().astype(np.float64)
    binary = _top(occupancy.ravel(), voxels).reshape(grid.shape)
    own = grid.centers().numpy()[binary].mean(0)
    move = np.rint((centre - own) / grid.voxel_size).astype(int)  # (x, y[, z]); the array's axes are reversed
    for k, step in enumerate(move):
        if step:
            binary = shifted(binary, grid.ndim - 1 - k, int(step))
    return binary


def _top(score: np.ndarray, count: int) -> np.ndarray:
    """Boolean mask of the ``count`` largest ``score`` entries (ties broken by order)."""
    mask = np.zeros(score.shape, dtype=bool)
    if count > 0:
        mask[np.argsort(-score, kind="stable")[:count]] = True
    return mask


def as_reconstruction(binary: np.ndarray, grid: Grid) -> Reconstruction:
    """A hand-made result of boolean ``binary``: its occupancy 0 or 1, threshold 0.5, no declared symmetry."""
    return Reconstruction(torch.from_numpy(binary.astype(np.float32)), grid, threshold=0.5)


def run_case(case: dict, cfg, makers: dict, resolution: int = 24) -> list[dict]:
    """Simulate, solve and check one case on a grid of ``resolution`` voxels per axis (3D; 2D twice as many pixels),
    then check its wrong candidates; one row per checked result."""
    ndim = case["ndim"]
    make = makers[case["shape"]][1]
    shape = make(RADIUS_MM)
    n = resolution * (2 if ndim == 2 else 1)
    grid = Grid(n, ndim, extent_around(shape.radius(), n, FILL))
    directions = directions_2d(angles_2d(case["dips"])) if ndim == 2 else fibonacci_hemisphere(case["dips"])
    sensor = LevelSensor(snr_db=case["snr_db"], seed=case["noise_seed"])
    _, measurement = simulate_measurement(shape, directions, grid=grid, sensor=sensor, seed=case["noise_seed"],
                                          progress=False)
    operator = instantiate(cfg.operator)(grid, measurement.directions, grid.n)
    solver = instantiate(cfg.solver, seed=case["noise_seed"])
    recon = solver.solve(measurement, operator)
    truth_occupancy = shape.occupancy(grid, supersample=3).numpy()
    truth = truth_occupancy > reference_level(truth_occupancy, grid, shape.volume)
    binary = recon.binary
    voxels = int(binary.sum())
    centre = data_centroid(measurement, operator)
    candidates = {"reconstruction": recon, "truth": as_reconstruction(truth, grid)}
    if voxels:
        candidates["ball"] = as_reconstruction(ball_candidate(grid, voxels, centre), grid)
        candidates["shifted"] = as_reconstruction(
            shifted(binary, case["shift_axis"], case["shift_sign"] * SHIFT_VOXELS), grid)
        candidates["other"] = as_reconstruction(
            other_shape_candidate(makers[case["other"]][1], grid, voxels, centre), grid)
    rows = []
    target = measured_profiles(measurement, operator)
    profiles_expected = estimate_slab_sigma(target) * math.sqrt(target.numel()) / float(target.norm())
    for kind, result in candidates.items():
        c = check_consistency(measurement, operator, result, warn=False)
        rows.append({**case, "n": grid.n, "kind": kind, "iou": iou(result.binary, truth),
                     "residual": c.profile_residual,
                     "residual_continuous": c.profile_residual_continuous, "expected_profiles": profiles_expected,
                     "expected": c.profile_residual_expected, "ratio": c.profile_residual / c.profile_residual_expected,
                     "limit": c.residual_limit, "noise_source": c.noise_source, "verdict": c.verdict,
                     "residual_flagged": c.profile_residual > c.residual_limit,
                     "findings": [w[:60] for w in c.warnings]})
    return rows


def band(snr: float | None) -> str:
    """The SNR band of a case."""
    for name, low, high in BANDS:
        if (snr is None and low is None) or (snr is not None and low is not None and low <= snr < high):
            return name
    raise ValueError(f"SNR {snr} lies in no band")


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> list[dict]:
    """Run the benchmark; returns one row per checked result (reconstructions and candidates)."""
    args = parse_args(argv)
    rng = start_pool_run(args)
    makers = shape_makers()
    names = shape_names(args.shapes)
    pools = {ndim: [name for name in makers if makers[name][0] == ndim] for ndim in (2, 3)}
    cases = [sample_case(rng, name, makers[name][0], pools[makers[name][0]])
             for _ in range(args.trials) for name in names]
    cfg = compose_job(JOB)
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for case in tqdm(cases, desc="cases"):
            rows.extend(run_case(case, cfg, makers, args.resolution))
    print_table(rows, args)
    if args.json:
        args.json.write_text(json.dumps([{k: v for k, v in r.items() if k != "flags"} for r in rows], indent=1))
    return rows


def _wrong(row: dict) -> bool:
    """Whether ``row`` is a wrong candidate: a hand-made one (not the reconstruction, not the truth) with IoU below
    ``WRONG_IOU``."""
    return row["kind"] in CANDIDATES and row["iou"] < WRONG_IOU


def _rate(flags: list[bool]) -> float:
    return sum(flags) / len(flags) if flags else float("nan")


def _quantiles(values: list[float]) -> str:
    if not values:
        return "- | - | -"
    v = np.asarray(values)
    return f"{np.median(v):.2f} | {np.quantile(v, 0.95):.2f} | {v.max():.2f}"


def _listed(items: list[str], most: int = 12) -> str:
    """``items`` joined, the first ``most`` of them and how many more."""
    more = f" and {len(items) - most} more" if len(items) > most else ""
    return (", ".join(items[:most]) + more) or "none"


def print_table(rows: list[dict], args: argparse.Namespace) -> None:
    """Per SNR band: the correct results' residual / expected and false alarms, the wrong candidates' detection
    under every rule; the misses of the current rule, and the ``RESULT`` line."""
    named = rules()
    for r in rows:
        r["band"] = band(r["snr_db"])
        r["flags"] = {key: r["residual"] > rule(r) for key, rule in named.items()}
    cases = len({(r["shape"], r["noise_seed"]) for r in rows})
    print(f"\n{args.trials} random scans per shape (seed {args.seed}), {cases} cases; solver=voxel. Correct: a "
          f"reconstruction with IoU >= {CORRECT_IOU:g}; wrong: a candidate ({', '.join(CANDIDATES)}) with IoU < "
          f"{WRONG_IOU:g}. Rules flag residual > the check's own limit (current), max(3 * expected, "
          f"{RESIDUAL_FLOOR:g}) (before), the check's limit with an unstated noise estimated from the profiles alone "
          f"(profiles), max(f * expected, {RESIDUAL_FLOOR:g}) (fN) or hypot(f * expected, "
          f"max({RESIDUAL_FLOOR:g}, {RESIDUAL_FLOOR_VOXELS:g} / n)) (hypotN)\n")
    recons = [r for r in rows if r["kind"] == "reconstruction"]
    groups = [*(name for name, *_ in BANDS), "all"]

    def correct_in(g: str) -> list[dict]:
        return [r for r in recons if g in ("all", r["band"]) and r["iou"] >= CORRECT_IOU]

    def wrong_in(g: str) -> list[dict]:
        return [r for r in rows if g in ("all", r["band"]) and _wrong(r)]

    print("| band | cases | correct | between | wrong recon. | correct: residual/expected median | 95% | max | "
          "false alarms (residual) | false alarms (verdict) | wrong candidates | wrong: residual/expected min | 5% "
          "| median |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for g in groups:
        picked = [r for r in recons if g in ("all", r["band"])]
        correct, wrong = correct_in(g), wrong_in(g)
        between = sum(WRONG_IOU <= r["iou"] < CORRECT_IOU for r in picked)
        ratios = np.sort([r["ratio"] for r in wrong])
        spread = (f"{ratios[0]:.2f} | {np.quantile(ratios, 0.05):.2f} | {np.median(ratios):.2f}" if ratios.size
                  else "- | - | -")
        print(f"| {g} | {len(picked)} | {len(correct)} | {between} | {sum(r['iou'] < WRONG_IOU for r in picked)} | "
              f"{_quantiles([r['ratio'] for r in correct])} | {_rate([r['residual_flagged'] for r in correct]):.3f} | "
              f"{_rate([r['verdict'] == 'inconsistent' for r in correct]):.3f} | {len(wrong)} | {spread} |")
    print("\nfalse alarms (share of correct results flagged) / detected (share of wrong candidates flagged)\n")
    print("| rule | " + " | ".join(groups) + " |\n|---|" + "---|" * len(groups))
    totals = {}
    for key in named:
        cells = []
        for g in groups:
            totals[key] = (_rate([r["flags"][key] for r in correct_in(g)]),
                           _rate([r["flags"][key] for r in wrong_in(g)]))
            cells.append(f"{totals[key][0]:.3f} / {totals[key][1]:.3f}")
        print(f"| {key} | " + " | ".join(cells) + " |")
    clean = [key for key in named if totals[key][0] == 0]
    best = max(clean, key=lambda key: totals[key][1], default=None)
    print(f"\nrules without a false alarm: {', '.join(clean) or 'none'}"
          + (f"; the most detections among them: {best} ({totals[best][1]:.3f})" if best else ""))
    print("detected per candidate kind (current rule): " + ", ".join(
        f"{kind} {sum(r['flags']['current'] for r in rows if r['kind'] == kind and _wrong(r))}/"
        f"{sum(r['kind'] == kind and _wrong(r) for r in rows)}" for kind in CANDIDATES))
    failed = [r for r in recons if r["iou"] < WRONG_IOU]
    print(f"wrong reconstructions (IoU < {WRONG_IOU:g}) flagged by the current rule: "
          f"{sum(r['flags']['current'] for r in failed)}/{len(failed)} "
          f"({_listed(sorted({r['shape'] for r in failed}))})")
    truths = [r for r in rows if r["kind"] == "truth"]
    print(f"the truth's own voxels flagged by the current rule: {sum(r['flags']['current'] for r in truths)}/"
          f"{len(truths)} ({_listed(sorted({r['shape'] for r in truths if r['flags']['current']}))}); their "
          f"residual/expected: median {np.median([r['ratio'] for r in truths]):.2f}, max "
          f"{max(r['ratio'] for r in truths):.2f}")
    missed = [f"{r['shape']}:{r['kind']} ({r['band']}, IoU {r['iou']:.2f}, residual {r['residual']:.3f} < "
              f"{r['limit']:.3f})" for r in rows if _wrong(r) and not r["flags"]["current"]]
    print(f"wrong candidates the current rule passes ({len(missed)}): {_listed(missed)}")
    alarms = [f"{r['shape']} ({r['band']}, IoU {r['iou']:.2f}, residual {r['residual']:.3f} > {r['limit']:.3f})"
              for r in recons if r["iou"] >= CORRECT_IOU and r["flags"]["current"]]
    print(f"correct results the current rule flags ({len(alarms)}): {_listed(alarms)}")
    print("RESULT " + " ".join(f"false_alarms_{key}={totals[key][0]:.3f} detected_{key}={totals[key][1]:.3f}"
                               for key in named) + f" cases={cases}")


if __name__ == "__main__":
    main()
