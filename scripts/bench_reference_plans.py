"""Reference-ball calibration under short scan plans, on rigs it has never seen: does each 90 % interval hold?

``scripts/bench_calibration.py`` calibrates with 123 Fibonacci dips. A user with a rig dips a reference ball
along fewer: this benchmark takes the guide's 16-dip grid plan (``grid16``: tilts 0/25/50/70 deg x spins
0/90/180/270 deg; tilt 0 a hair above 0, so that its spins stay four dips) and 41 Fibonacci directions
(``fibonacci41``, the few-dip budget of ``bench_quality.py``); ``--plans grid16_35`` adds a rig that tilts no further
than 35 deg, as the authors' did (tilts 0/12/24/35 deg x the same spins). ``--rigs`` rig geometries are drawn as in
``bench_calibration.py`` (:func:`dipnet.experiments.random_rigs.draw_rig`: pivot +-60 mm, offset +-40 mm, zeros
+-5 deg, step scale +-3 %, section +-20 %, a drift of up to +-0.5 mm over a 16-dip session, a lag of 0-0.5 s; fixed
``--seed``), and on each a 30 mm ball is dipped along each plan at ``--snr`` dB, twice: centred on the spin axis
(``ball``) and ``--ball-offset`` mm off it (``offball``), held off its assumed place by a normal error of sd
0.3 mm along every axis and its recorded start height off the water line by another.

For every (plan, ball, parameter) it prints how many rigs leave the parameter determined, how many of those
intervals hold the true value, and the mean and spread of the standardised error (error / the reported
standard error: about 0 and 1 when the report is honest). Last line ``RESULT grid16_ball_coverage90=<>
grid16_offball_coverage90=<> fibonacci41_ball_coverage90=<> fibonacci41_offball_coverage90=<>
worst_parameter_coverage90=<> worst_parameter=<>`` (coverage over the determined (rig, parameter) pairs of
each case; the worst single parameter of any case that is determined on at least 5 rigs, ``none`` when every
interval held).

    python scripts/bench_reference_plans.py           # 24 rigs
    python scripts/bench_reference_plans.py --quick   # 5 rigs
    python scripts/bench_reference_plans.py --plans grid16_35   # a rig that tilts to 35 deg
"""

from __future__ import annotations

import argparse
import logging
import warnings

import numpy as np
import torch
from tqdm.auto import tqdm

from dipnet.core.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.random_rigs import (BALL_POSITION_SD_MM, BALL_RADIUS, START_HEIGHT_SD_MM, covered, draw_rig,
                                           reference_ball)
from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank
from dipnet.experiments.bench_options import count_type, number_type, refuse_bad_run_options, thread_count
from dipnet.jobs.cli import user_errors

GRID_SPINS = (0.0, 90.0, 180.0, 270.0)


def grid_plan(tilts: tuple[float, ...]) -> np.ndarray:
    """Unit directions ``(len(tilts) * 4, 3)`` of a grid plan: each tilt (deg) at spins 0/90/180/270 deg."""
    return rig_to_direction([t for t in tilts for _ in GRID_SPINS], [s for _ in tilts for s in GRID_SPINS])


PLANS = {"grid16": grid_plan((1e-6, 25.0, 50.0, 70.0)), "fibonacci41": fibonacci_hemisphere(41),
         "grid16_35": grid_plan((1e-6, 12.0, 24.0, 35.0))}
SESSION_DIPS = 16  # the drift is drawn over a session of this many dips, whatever the plan
MIN_DETERMINED = 5  # a parameter determined on fewer rigs does not count for worst_parameter_coverage90


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rigs", type=count_type(1, "random rigs"), default=24, help="random rig geometries")
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR (dB)")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--ball-offset", type=number_type("mm off the spin axis", at_least=0), default=25.0, metavar="MM",
                   help="the second ball's centre off the spin axis (along x, mm)")
    p.add_argument("--plans", nargs="+", choices=list(PLANS), default=["grid16", "fibonacci41"],
                   help="the plans to dip the ball along")
    p.add_argument("--threads", type=thread_count, default=2, help="torch threads")
    p.add_argument("--quick", action="store_true", help="5 rigs")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), rigs=5)
    refuse_bad_run_options(p, args)  # --snr, --seed: now, not at the first rig
    return args


def standard_errors(report, truth: dict[str, float]) -> dict[str, float]:
    """Each determined parameter's error over its reported standard error."""
    return {name: (report.estimates[name] - truth[name]) / report.standard_errors[name]
            for name in report.determined if name in truth and report.standard_errors.get(name, 0.0) > 0}


def main(argv=None) -> dict[tuple[str, str], dict[str, list]]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any case."""
    with user_errors():
        return run(argv)


def run(argv=None) -> dict[tuple[str, str], dict[str, list]]:
    """Run the benchmark; returns, per (plan, ball), parameter -> ``[(covered, z), ...]`` over the rigs."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.getLogger("dipnet").setLevel(logging.ERROR)
    tank, protocol = Tank.default(3), DipProtocol()
    rng = np.random.default_rng(args.seed)
    offsets = {"ball": 0.0, "offball": args.ball_offset}
    found: dict[tuple[str, str], dict[str, list]] = {(p, b): {} for p in args.plans for b in offsets}
    reach = BALL_RADIUS + args.ball_offset + 60.0  # the stage travel of a dip (mm), as bench_calibration's
    session_s = SESSION_DIPS * (protocol.n_readings(reach) * protocol.settle_s + protocol.reorient_s)
    for i in tqdm(range(args.rigs), desc="rigs"):
        true = draw_rig(rng, tank.cross_section_mm2, session_s)
        held = np.random.default_rng(args.seed + 1000 + i).normal(0.0, BALL_POSITION_SD_MM, 3)
        start_error = float(np.random.default_rng(args.seed + 9000 + i).normal(0.0, START_HEIGHT_SD_MM))
        for plan in args.plans:
            for ball, offset in offsets.items():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)
                    _, report = reference_ball(offset, (offset + held[0], held[1], held[2]), raw_kwargs=dict(
                        directions=PLANS[plan], tank=tank, protocol=protocol, geometry=true,
                        sensor=LevelSensor(snr_db=args.snr, seed=1000 + i)), seed=i, start_error_mm=start_error)
                z = standard_errors(report, true.to_dict())
                for name, ok in covered(report, true.to_dict()):
                    found[(plan, ball)].setdefault(name, []).append((ok, z.get(name, float("nan"))))
    print_table(found, args)
    return found


def print_table(found: dict[tuple[str, str], dict[str, list]], args: argparse.Namespace) -> None:
    """The per-parameter table and the ``RESULT`` line."""
    print(f"\n{args.rigs} rigs (seed {args.seed}), {args.snr:g} dB, the second ball {args.ball_offset:g} mm off the "
          f"spin axis\n")
    print("| plan | ball | parameter | determined | covered | mean z | sd z |\n|---|---|---|---|---|---|---|")
    coverage, worst = {}, (float("inf"), "none")
    for (plan, ball), params in found.items():
        pairs = [ok for rows in params.values() for ok, _ in rows]
        coverage[f"{plan}_{ball}"] = float(np.mean(pairs)) if pairs else float("nan")
        for name, rows in sorted(params.items()):
            ok = np.array([r[0] for r in rows])
            z = np.array([r[1] for r in rows])
            print(f"| {plan} | {ball} | {name} | {len(rows)}/{args.rigs} | {ok.sum()}/{len(rows)} | "
                  f"{np.nanmean(z):+.2f} | {np.nanstd(z):.2f} |")
            if len(rows) >= MIN_DETERMINED and ok.mean() < worst[0]:
                worst = (float(ok.mean()), f"{plan}:{ball}:{name}")
    if worst[0] >= 1.0:  # every interval held: no parameter is the worst
        worst = (1.0, "none")
    print("RESULT " + " ".join(f"{key}_coverage90={value:.3f}" for key, value in coverage.items())
          + f" worst_parameter_coverage90={worst[0]:.3f} worst_parameter={worst[1]}")


if __name__ == "__main__":
    main()
