"""Does the consistency check tell a declared symmetry the object has from one it lacks? Random dips, many shapes.

A symmetry declared for the object (the top-level ``symmetry`` option's images of the dips, or a solver's
symmetry prior) makes the shape symmetric whatever the dips say; the consistency check tests the declaration
against the dips' moments (:mod:`dipnet.preprocessing.symmetry_moments`) and names it when the dips reject it.
This benchmark dips the 2D built-in shapes (disk, chamber box, elephant), the 3D ones (ball, box, torus, chamber
box) and the 16 bundled meshes (scaled to 45 mm, on a 32-voxel grid of 100 mm), each under declarations it has
and lacks: 2D a mirror across x, across y and a 2- or 3-fold rotation; 3D mirrors across x and y and 2- and
4-fold rotations about z; the ball and the tori (the built-in one and the bundled mesh) also their own groups,
and the chamber box a mirror across z (its chamber lies off that plane). ``--shapes`` picks some of them
(``disk_2d``, ``ball_3d``, ``bunny``...).

Each (shape, declaration) is first classed by its misfit on 123 noise-free dips (80 in 2D): **symmetric** (below
0.002: the object has the symmetry), **asymmetric** (above 0.05) or **near** (between: nearly symmetric objects
and asymmetry that moves little material). Then ``--trials`` random scans per shape (seeded by ``--seed``) draw a
number of dips (12-80; 2D 8-40), a noise (20-40 dB, or noise-free one time in five) and a noise seed, and every
declaration is tested on them. The table gives, per class, how often the check rejected the declaration; last
line ``RESULT false_rejections=<> detected_asymmetric=<> detected_near=<> trials=<>`` (the shares of symmetric
trials rejected, target 0, and of asymmetric and near ones rejected, target 1 for asymmetric).

    python scripts/bench_symmetry_check.py            # 8 scans per shape
    python scripts/bench_symmetry_check.py --quick    # 2 scans per shape
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from tqdm.auto import tqdm

from dipnet.core.grid import Grid
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.shape_pool import shape_makers, shape_names, start_pool_run
from dipnet.preprocessing.symmetry_moments import P_LIMIT, group_closure, symmetry_fit
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.priors import symmetry_maps
from dipnet.experiments.bench_options import count_type, refuse_bad_run_options, thread_count
from dipnet.jobs.cli import user_errors

RADIUS_MM, EXTENT_MM, RESOLUTION = 45.0, 100.0, 32
DECLARATIONS = {
    2: {"mirror_x": {"plane_normal": [1, 0]}, "mirror_y": {"plane_normal": [0, 1]}, "rotation2": {"order": 2},
        "rotation3": {"order": 3}},
    3: {"mirror_x": {"plane_normal": [1, 0, 0]}, "mirror_y": {"plane_normal": [0, 1, 0]},
        "rotation2_z": {"axis": [0, 0, 1], "order": 2}, "rotation4_z": {"axis": [0, 0, 1], "order": 4}},
}
TORUS = {"rotation6_z": {"axis": [0, 0, 1], "order": 6}, "mirror_z": {"plane_normal": [0, 0, 1]}}
EXTRA_DECLARATIONS = {"ball_3d": {"dihedral4_z": {"plane_normal": [1, 0, 0], "axis": [0, 0, 1], "order": 4}},
                      "torus_3d": TORUS, "torus": TORUS,  # the built-in torus and the bundled mesh, both about z
                      "chamber_box_3d": {"mirror_z": {"plane_normal": [0, 0, 1]}}}
SYMMETRIC_BELOW, ASYMMETRIC_ABOVE = 0.002, 0.05
REFERENCE_DIPS = {2: 80, 3: 123}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=count_type(1, "random scans per shape"), default=8, help="random scans per shape")
    p.add_argument("--shapes", nargs="+", metavar="NAME",
                   help="the shapes to dip (default: all; names as in the table, e.g. elephant_2d ball_3d bunny)")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--threads", type=thread_count, default=2, help="torch threads")
    p.add_argument("--quick", action="store_true", help="2 scans per shape")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), trials=2)
    refuse_bad_run_options(p, args)  # --seed
    return args


def shapes(names: list[str] | None = None) -> list[tuple[str, int, object]]:
    """``(name, ndim, shape)`` of the shapes the benchmark dips: all, or those called ``names`` (a ``ValueError``
    naming the known ones for any other)."""
    makers = shape_makers()
    return [(name, makers[name][0], makers[name][1](RADIUS_MM)) for name in shape_names(names)]


def declarations(name: str, ndim: int) -> dict[str, np.ndarray]:
    """The groups ``(G, d, d)`` declared for shape ``name``, by declaration name."""
    specs = {**DECLARATIONS[ndim], **EXTRA_DECLARATIONS.get(name, {})}
    return {key: group_closure([m.numpy() for m in symmetry_maps(ndim, **spec)]) for key, spec in specs.items()}


def scan(shape, ndim: int, n_dips: int, snr_db: float | None, seed: int):
    """The preprocessed measurement of ``shape`` along ``n_dips`` directions at ``snr_db`` (``None``: noise-free)."""
    directions = directions_2d(angles_2d(n_dips)) if ndim == 2 else fibonacci_hemisphere(n_dips)
    sensor = LevelSensor(snr_db=snr_db, seed=seed) if snr_db is not None else None
    return simulate_measurement(shape, directions, grid=Grid(RESOLUTION, ndim, EXTENT_MM), sensor=sensor, seed=seed,
                                progress=False)[1]


def classify(misfit: float) -> str:
    """The class of a declaration by its noise-free misfit."""
    return "symmetric" if misfit < SYMMETRIC_BELOW else "asymmetric" if misfit > ASYMMETRIC_ABOVE else "near"


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> list[dict]:
    """Run the benchmark; returns one row per (shape, declaration, trial)."""
    args = parse_args(argv)
    rng = start_pool_run(args)
    rows = []
    for name, ndim, shape in tqdm(shapes(args.shapes), desc="shapes"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            groups = declarations(name, ndim)
            reference = scan(shape, ndim, REFERENCE_DIPS[ndim], None, 0)
            classes = {key: (classify(fit.misfit), fit.misfit)
                       for key, fit in ((key, symmetry_fit(reference, group)) for key, group in groups.items())}
            for trial in range(args.trials):
                n_dips = int(rng.integers(8, 41) if ndim == 2 else rng.integers(12, 81))
                snr = None if rng.random() < 0.2 else float(rng.uniform(20.0, 40.0))
                measurement = scan(shape, ndim, n_dips, snr, int(rng.integers(1 << 30)))
                for key, group in groups.items():
                    fit = symmetry_fit(measurement, group)
                    rows.append({"shape": name, "declared": key, "class": classes[key][0],
                                 "reference_misfit": classes[key][1], "dips": n_dips, "snr_db": snr,
                                 "misfit": fit.misfit, "p_value": fit.p_value, "rejected": fit.rejected})
    print_table(rows, args)
    return rows


def print_table(rows: list[dict], args: argparse.Namespace) -> None:
    """Per class the rejection counts, the misfits of the rejected and kept, and the ``RESULT`` line."""
    print(f"\n{args.trials} random scans per shape (seed {args.seed}); classes by the misfit on noise-free "
          f"reference dips (symmetric < {SYMMETRIC_BELOW:g} < near < {ASYMMETRIC_ABOVE:g} < asymmetric)\n")
    print("| class | declarations | trials | rejected | share | misfit median | largest misfit with p < "
          f"{P_LIMIT:g} | smallest misfit rejected |\n|---|---|---|---|---|---|---|---|")
    share = {}
    for cls in ("symmetric", "near", "asymmetric"):
        picked = [r for r in rows if r["class"] == cls]
        rejected = sum(r["rejected"] for r in picked)
        share[cls] = rejected / len(picked) if picked else float("nan")
        pairs = len({(r["shape"], r["declared"]) for r in picked})
        median = float(np.nanmedian([r["misfit"] for r in picked])) if picked else float("nan")
        significant = max((r["misfit"] for r in picked if r["p_value"] < P_LIMIT), default=float("nan"))
        smallest = min((r["misfit"] for r in picked if r["rejected"]), default=float("nan"))
        print(f"| {cls} | {pairs} | {len(picked)} | {rejected} | {share[cls]:.3f} | {median:.4f} | {significant:.4f} | "
              f"{smallest:.4f} |")
    missed = [f"{r['shape']}:{r['declared']} ({r['dips']} dips)" for r in rows
              if r["class"] == "asymmetric" and not r["rejected"]]
    wrong = [f"{r['shape']}:{r['declared']} ({r['dips']} dips)" for r in rows
             if r["class"] == "symmetric" and r["rejected"]]
    print(f"\nasymmetric declarations kept: {', '.join(missed) or 'none'}")
    print(f"symmetric declarations rejected: {', '.join(wrong) or 'none'}")
    near = sorted({(r["shape"], r["declared"], r["reference_misfit"]) for r in rows if r["class"] == "near"},
                  key=lambda n: n[2])
    print("near declarations (noise-free misfit, rejected / trials): " + ", ".join(
        f"{s}:{d} {m:.4f} {sum(r['rejected'] for r in rows if (r['shape'], r['declared']) == (s, d))}/"
        f"{sum((r['shape'], r['declared']) == (s, d) for r in rows)}" for s, d, m in near))
    print(f"RESULT false_rejections={share['symmetric']:.3f} detected_asymmetric={share['asymmetric']:.3f} "
          f"detected_near={share['near']:.3f} trials={len(rows)}")


if __name__ == "__main__":
    main()
