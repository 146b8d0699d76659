"""Calibrate a dipping rig from dips of a reference ball and write a rig calibration file.

Dip a ball of known radius (held with its centre at the object origin the rig assumes, or at
``--centre``) at a few orientations, e.g. with ``scripts/scan.py`` and a grid plan of tilts
0-60 deg x a few spins, then:

    python scripts/calibrate.py scans/ball/rawscan.jsonl --ball-radius 30 --tank lab-tank-1 \\
        --output rig_calibration.yaml

The file (:mod:`dipnet.rig.calibration_file`) names the scan's rig and the given tank; scans
use it with ``rig.calibration=rig_calibration.yaml`` (and ``+rig.tank=lab-tank-1``), readers with
``source.reader.calibration=rig_calibration.yaml``. The parameters the dips cannot determine
are refused with a message naming them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dipnet.calibration import PARAMETERS, calibrate_reference
from dipnet.cli import user_errors
from dipnet.grid import Grid
from dipnet.rawscan import read_rawscan
from dipnet.rig.calibration_file import TANK_CONFIG_KEY, Calibration, save_calibration
from dipnet.shapes import Ball

DEFAULT_PARAMS = ("pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "cross_section_mm2")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scan", type=Path, help="raw scan (.jsonl) of the reference ball")
    p.add_argument("--ball-radius", type=float, required=True, help="the ball's radius (mm)")
    p.add_argument("--centre", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                   help="the ball's centre in the object frame (mm)")
    p.add_argument("--tank", help="the tank's identity (default: the scan's header.config['tank_id'])")
    p.add_argument("--params", nargs="+", default=list(DEFAULT_PARAMS), choices=list(PARAMETERS),
                   help="geometry parameters to estimate")
    p.add_argument("--n", type=int, default=48, help="grid resolution for the ball's occupancy")
    p.add_argument("--output", type=Path, default=Path("rig_calibration.yaml"), help="calibration file (.yaml/.json)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    with user_errors():
        raw = read_rawscan(args.scan)
        tank = args.tank or raw.header.config.get(TANK_CONFIG_KEY)
        if not tank:
            raise ValueError(f"{args.scan} does not name its tank: pass --tank")
        ball = Ball(args.ball_radius, center=tuple(args.centre))
        reach = args.ball_radius + max(abs(c) for c in args.centre)
        grid = Grid(args.n, 3, extent=2.0 * (reach + 15.0))  # room for the start heights still to be found
        geometry, report = calibrate_reference(raw, ball, grid, args.params)
        calibration = Calibration(geometry, rig=raw.header.rig, tank=str(tank), method="reference",
                                  uncertainty={k: v for k, v in report.standard_errors.items() if k in report.estimates},
                                  notes=f"ball r={args.ball_radius:g} mm at {list(args.centre)} from {args.scan}")
        path = save_calibration(calibration, args.output)
    print(report.table())
    print(f"wrote {path} (rig {raw.header.rig!r}, tank {tank!r})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
