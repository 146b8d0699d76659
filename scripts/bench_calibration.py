"""Calibration on rigs it has never seen: random rig geometries, self-calibration and a reference ball.

``--rigs`` rig geometries are drawn at random (fixed ``--seed``) over the calibrated range:
pivot +-60 mm, tilt-axis offset +-40 mm, tilt and spin zeros +-5 deg, cross-section +-20 %,
step scale +-3 %, a level drift of up to +-0.5 mm over the session and a sensor lag of
0-0.5 s. Rig ``i`` dips bundled mesh ``MESHES[i % 4]`` (scaled to ``--fill`` of the working ball
on an ``--n``^3 grid) along ``--dips`` Fibonacci directions with ``--snr`` dB of level noise,
and a 30 mm reference ball along the same directions, twice: centred on the spin axis, and
``--ball-offset`` mm (default 25) off it; each held with its centre off the assumed position by a normal
error of standard deviation 0.3 mm along every axis, its recorded start height off the water line by
another (90 % of each within the calibration's default 0.5 mm tolerances). The voxel solver then
reconstructs the mesh (i) with the nominal geometry, (ii) self-calibrated
(:func:`dipnet.calibration.self_calibration.self_calibrate`, the cross-section fitted with the
implicit field's shape, the final shape by the voxel solver),
(iii) with the true geometry, (iv) with each ball's reference calibration
(:func:`dipnet.calibration.reference.calibrate_reference`): ``ball`` (centred) compared with the
truth turned by the spin zero (a centred ball's symmetry: never estimated), ``offball`` with the
truth itself (a ball off the axis shows the spin zero).

Self-calibration cannot see two gauges of an unknown object, the spin zero (its own rotation)
and the step scale (the scale of the whole scene); they stay at the configured 0 and 1 and the
report names them. So the calibrated shape is compared with the truth both as it is
(``calibrated``) and moved by those two gauges (``gauged``: rotated by the spin zero, scaled by
1 / step scale about the stage-0 water line), and the self-calibrated pivot and offset are
compared with their gauge-equivalent values (``p' = (1 - l) t0 + l p``, ``e' = l e``, ``A' = l^3 A``
for the cross-section, ``l`` = 1 / step scale: the scene seen at step scale 1 is ``l`` times the true one,
its volume ``l^3`` times, for the same level rises). Coverage counts, over (rig, parameter) pairs marked determined, how
often the 90% interval holds the true value.

Prints a table per rig and last ``RESULT median_calibrated_over_true=<> worst_calibrated_over_true=<>
coverage90=<> refused=<> ball_coverage90=<> median_gauged_over_true=<> worst_gauged_over_true=<>
median_ball_over_true=<> worst_ball_over_true=<> offball_coverage90=<> median_offball_over_true=<>
worst_offball_over_true=<>`` (Chamfer ratios; ``refused`` the fraction of rigs where any stage raised).

    python scripts/bench_calibration.py            # 20 rigs at 48^3, 123 dips, 30 dB
    python scripts/bench_calibration.py --quick    # 3 rigs at 32^3
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
import warnings
from pathlib import Path
from dataclasses import replace

import numpy as np
import torch

from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.experiments.random_rigs import (BALL_POSITION_SD_MM, START_HEIGHT_SD_MM, covered, draw_rig,
                                           reference_ball)
from dipnet.calibration.self_calibration import self_calibrate
from dipnet.preprocessing.datasets import mesh_path
from dipnet.core.grid import Grid
from dipnet.evaluation.metrics import evaluate
from dipnet.operators import make_operator
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank, simulate_scan
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.geometry import RigGeometry, invert_scan
from dipnet.shapes import load_mesh
from dipnet.shapes.mesh import MeshShape
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.voxel import VoxelSolver
from dipnet.experiments.bench_options import (count_type, grid_size_type, number_type, refuse_bad_run_options,
                                              thread_count)
from dipnet.jobs.cli import user_errors

MESHES = ("bunny", "hammer", "part_B13", "spot")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rigs", type=count_type(1, "random rigs"), default=20, help="random rig geometries")
    p.add_argument("--n", type=grid_size_type(3), default=48, help="grid resolution N")
    p.add_argument("--dips", type=count_type(1, "dips"), default=123, help="number of dips (Fibonacci hemisphere)")
    p.add_argument("--snr", type=float, default=30.0, help="level-sensor SNR (dB)")
    p.add_argument("--fill", type=float, default=0.8, help="mesh radius / working-ball radius")
    p.add_argument("--iterations", type=count_type(1, "solver iterations"), default=300,
                   help="voxel solver iterations per shape step")
    p.add_argument("--quick", action="store_true", help="3 rigs at 32^3, 80 solver iterations")
    p.add_argument("--threads", type=thread_count, default=2, help="torch threads")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--ball-offset", type=number_type("mm off the spin axis", at_least=0), default=25.0,
                   metavar="MM", help="the second ball's centre off the spin axis (along x, mm)")
    p.add_argument("--json", type=Path, metavar="PATH",
                   help="also write every rig's truth, estimates and intervals here")
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), rigs=3, n=32, iterations=80)
    refuse_bad_run_options(p, args)  # --snr, --seed, --fill, --json: now, not at the first rig or after it
    return args


def gauged_truth(shape: MeshShape, true: RigGeometry, t0: float) -> MeshShape:
    """The truth as self-calibration sees it with spin zero 0 and step scale 1: turned about the spin
    axis by the spin zero and scaled by 1 / step scale about the stage-0 water line ``(0, 0, t0)``."""
    lam, a = 1.0 / true.step_scale, np.radians(true.spin_zero_deg)
    turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    mesh = shape.mesh.copy()
    mesh.vertices = lam * mesh.vertices @ turn.T + np.array([0.0, 0.0, (1.0 - lam) * t0])
    return MeshShape(mesh, name=f"{shape.name} (gauged)")


def self_truth(true: RigGeometry, t0: float) -> dict[str, float]:
    """The true values self-calibration can reach at the configured step scale 1: pivot and offset in the
    stage's length unit, the cross-section that turns the rises into the volume of the scene scaled by
    ``l`` = 1 / step scale (``l^3`` times the true section)."""
    lam = 1.0 / true.step_scale
    return {"pivot_mm": (1 - lam) * t0 + lam * true.pivot_mm, "tilt_axis_offset_mm": lam * true.tilt_axis_offset_mm,
            "tilt_zero_deg": true.tilt_zero_deg, "level_drift_mm_per_s": true.level_drift_mm_per_s,
            "cross_section_mm2": lam**3 * true.cross_section_mm2}


def main(argv=None) -> list[dict]:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2."""
    with user_errors():
        return run(argv)


def run(argv=None) -> list[dict]:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.getLogger("dipnet").setLevel(logging.ERROR)  # the reports' warnings are in the table
    grid = Grid(args.n, 3)
    tank, protocol = Tank.default(3), DipProtocol()
    rng = np.random.default_rng(args.seed)
    directions = fibonacci_hemisphere(args.dips)
    rows, cover, ball_cover, offball_cover, refused = [], [], [], [], 0
    print(f"{'rig':>3} {'mesh':<9} {'pivot':>6} {'offset':>6} {'tilt0':>5} {'spin0':>5} {'step':>6} {'section':>7}"
          f" | {'nominal':>7} {'calib.':>7} {'gauged':>7} {'ball':>7} {'offball':>7} {'true':>7} {'c/t':>5} {'g/t':>5}"
          f" {'b/t':>5} {'o/t':>5} | {'self cov':>8} {'ball cov':>8} {'off cov':>8} {'s':>5}", flush=True)
    for i in range(args.rigs):
        name = MESHES[i % len(MESHES)]
        shape = load_mesh(mesh_path(name), radius=args.fill * grid.radius)
        radius = float(shape.radius())
        session = args.dips * (protocol.n_readings(radius + 60.0) * protocol.settle_s + protocol.reorient_s)
        true = draw_rig(rng, tank.cross_section_mm2, session)
        t_start = time.perf_counter()
        raw = simulate_scan(shape, directions, tank=tank, protocol=protocol, geometry=true,
                            sensor=LevelSensor(snr_db=args.snr, seed=i), progress=False)
        solver = VoxelSolver(iterations=args.iterations, seed=args.seed, progress=False)
        truth = shape.occupancy(grid, supersample=3).numpy() >= 0.5
        scores = {}
        for case, geometry in (("nominal", None), ("true", true)):
            m = preprocess(raw if geometry is None else invert_scan(raw, geometry), grid=grid, t_start="metadata")
            try:
                recon = solver.solve(m, make_operator(grid, m.directions, grid.n))
                scores[case] = evaluate(recon, truth, grid, truth_mesh=shape.mesh)["chamfer"]
            except ValueError:  # the nominal geometry may put every profile outside the grid
                scores[case] = float("nan")
        row = {"rig": i, "mesh": name, "true": true.to_dict()}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                result = self_calibrate(raw, grid, solver, seed=i,
                                        gain_solver=ImplicitSolver(seed=args.seed, progress=False))
                held = np.random.default_rng(args.seed + 1000 + i).normal(0.0, BALL_POSITION_SD_MM)
                shifted = np.random.default_rng(args.seed + 5000 + i).normal(0.0, BALL_POSITION_SD_MM, 2)
                start_error = np.random.default_rng(args.seed + 9000 + i).normal(0.0, START_HEIGHT_SD_MM)
                balls = {key: reference_ball(offset, (offset + shifted[0], shifted[1], held), raw_kwargs=dict(
                    directions=directions, tank=tank, protocol=protocol, geometry=true,
                    sensor=LevelSensor(snr_db=args.snr, seed=1000 + i)), seed=i, start_error_mm=start_error)
                    for key, offset in (("ball", 0.0), ("offball", args.ball_offset))}
        except ValueError as exc:
            refused += 1
            print(f"{i:>3} {name:<9} refused: {exc}", flush=True)
            rows.append({**row, "refused": str(exc)})
            continue
        t0 = float(raw.header.t_start_mm)
        scores["calibrated"] = evaluate(result.reconstruction, truth, grid, truth_mesh=shape.mesh)["chamfer"]
        gauged = gauged_truth(shape, true, t0)
        scores["gauged"] = evaluate(result.reconstruction, gauged.occupancy(grid, supersample=3).numpy() >= 0.5, grid,
                                    truth_mesh=gauged.mesh)["chamfer"]
        for key, (ball_geometry, ball_report) in balls.items():
            m = preprocess(invert_scan(raw, ball_geometry), grid=grid, t_start="metadata")
            turned = gauged_truth(shape, replace(true, step_scale=1.0), t0) \
                if "spin_zero_deg" in ball_report.undetermined else shape  # a centred ball: the spin zero's gauge
            scores[key] = evaluate(solver.solve(m, make_operator(grid, m.directions, grid.n)),
                                   turned.occupancy(grid, supersample=3).numpy() >= 0.5, grid,
                                   truth_mesh=turned.mesh)["chamfer"]
        self_cov = covered(result.report, self_truth(true, t0))
        ball_cov = covered(balls["ball"][1], true.to_dict())
        offball_cov = covered(balls["offball"][1], true.to_dict())
        cover += [c for _, c in self_cov]
        ball_cover += [c for _, c in ball_cov]
        offball_cover += [c for _, c in offball_cov]
        row.update(ball_position_error_mm=[*shifted, held], ball_start_height_error_mm=start_error, scores=scores,
                   self_covered=self_cov, ball_covered=ball_cov, offball_covered=offball_cov,
                   self_estimates=result.report.estimates, self_truth=self_truth(true, t0),
                   self_intervals=result.report.intervals,
                   self_history=result.history, seconds=time.perf_counter() - t_start,
                   **{f"{key}_{part}": getattr(report, part) for key, (_, report) in balls.items()
                      for part in ("estimates", "intervals")})
        rows.append(row)
        if args.json:  # after every rig, so an interrupted run keeps what it measured
            with open(args.json, "w") as f:
                json.dump(rows, f, indent=1, default=float)
        print(f"{i:>3} {name:<9} {true.pivot_mm:6.1f} {true.tilt_axis_offset_mm:6.1f} {true.tilt_zero_deg:5.1f} "
              f"{true.spin_zero_deg:5.1f} {true.step_scale:6.3f} {true.cross_section_mm2 / tank.cross_section_mm2:7.3f}"
              f" | {scores['nominal']:7.4f} {scores['calibrated']:7.4f} {scores['gauged']:7.4f} {scores['ball']:7.4f}"
              f" {scores['offball']:7.4f} {scores['true']:7.4f} {scores['calibrated'] / scores['true']:5.2f}"
              f" {scores['gauged'] / scores['true']:5.2f} {scores['ball'] / scores['true']:5.2f}"
              f" {scores['offball'] / scores['true']:5.2f} | "
              f"{sum(c for _, c in self_cov)}/{len(self_cov):<6} {sum(c for _, c in ball_cov)}/{len(ball_cov):<6}"
              f" {sum(c for _, c in offball_cov)}/{len(offball_cov):<6} {row['seconds']:5.0f}", flush=True)
        missed = [n for n, c in self_cov if not c] + [f"ball:{n}" for n, c in ball_cov if not c] + \
            [f"offball:{n}" for n, c in offball_cov if not c]
        if missed:
            print(f"    outside their 90% interval: {', '.join(missed)}", flush=True)
    done = [r for r in rows if "scores" in r]
    ratios = [r["scores"]["calibrated"] / r["scores"]["true"] for r in done]
    gauged = [r["scores"]["gauged"] / r["scores"]["true"] for r in done]
    ball = [r["scores"]["ball"] / r["scores"]["true"] for r in done]
    offball = [r["scores"]["offball"] / r["scores"]["true"] for r in done]
    nominal = [r["scores"]["nominal"] / r["scores"]["true"] for r in done if np.isfinite(r["scores"]["nominal"])]
    print(f"\n{len(done)} of {args.rigs} rigs at {args.n}^3, {args.dips} dips, {args.snr:g} dB, the second ball "
          f"{args.ball_offset:g} mm off the spin axis; Chamfer over true: "
          f"nominal median {statistics.median(nominal) if nominal else float('nan'):.2f} "
          f"({args.rigs - len(done) + sum(1 for r in done if not np.isfinite(r['scores']['nominal']))} unusable)")
    print(f"RESULT median_calibrated_over_true={statistics.median(ratios):.3f} "
          f"worst_calibrated_over_true={max(ratios):.3f} coverage90={np.mean(cover):.3f} "
          f"refused={refused / args.rigs:.3f} ball_coverage90={np.mean(ball_cover):.3f} "
          f"median_gauged_over_true={statistics.median(gauged):.3f} worst_gauged_over_true={max(gauged):.3f} "
          f"median_ball_over_true={statistics.median(ball):.3f} worst_ball_over_true={max(ball):.3f} "
          f"offball_coverage90={np.mean(offball_cover):.3f} median_offball_over_true={statistics.median(offball):.3f} "
          f"worst_offball_over_true={max(offball):.3f}")
    return rows


if __name__ == "__main__":
    main()
