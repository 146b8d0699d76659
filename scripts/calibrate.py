"""Calibrate a dipping rig from dips of a reference ball and write a rig calibration file.

Dip a ball of known radius (held with its centre at the object origin the rig assumes, or at
``--centre``) at a few orientations, e.g. with ``scripts/scan.py`` and a grid plan of tilts
0-60 deg x a few spins, then:

    python scripts/calibrate.py scans/ball/rawscan.jsonl --ball-radius 30 --tank lab-tank-1 \\
        --output rig_calibration.yaml

The file (:mod:`dipnet.core.calibration_file`) names the scan's rig and its tank (``--tank``, or the
tank the scan recorded with ``scan.py +rig.tank=lab-tank-1``; a different ``--tank`` is refused); scans
use it with ``+rig.calibration=rig_calibration.yaml`` (and ``+rig.tank=lab-tank-1``), readers with
``source.reader.calibration=rig_calibration.yaml``. A file already at ``--output`` is kept, renamed with its
modification time (``rig_calibration.20261130T194012.yaml``). Every parameter is estimated by default;
those the dips cannot determine (a centred ball's spin zero, by its symmetry) are named with
the reason and written under ``not_estimated`` with their configured values. A ball off the spin
axis has its distance from the axis fitted: its fitted centre is printed and written as
``reference_centroid_mm``, with a warning when it is farther than ``--position-tolerance`` from
``--centre`` (the ball is not mounted where stated). The level sensor's lag is never estimated: a known one
(``--sensor-lag``, s) is undone in every dip and written to the file. A balance reads the displaced volume, and
the water line's rise is that volume over the tank's section, which a ball's dips cannot tell from the step scale:
how well the section is known (``--section-tolerance``, relative; the section the scan records, or
``--cross-section``) bounds the step scale's interval (+-0.8 % with the default, the calibrated range +-20 %).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from dipnet.calibration.model import DEFAULT_REFERENCE, PARAMETERS, to_calibration
from dipnet.calibration.reference import calibrate_reference, check_reference_options
from dipnet.jobs.cli import user_errors
from dipnet.jobs.warnings_once import log_warnings_once
from dipnet.core.geometry import MAX_SENSOR_LAG_S, RigGeometry
from dipnet.core.grid import Grid
from dipnet.preprocessing.recorded import read_scan
from dipnet.core.calibration_file import keep_previous, save_calibration, scan_tank
from dipnet.shapes import Ball


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scan", type=Path, help="raw scan (.jsonl, or the authors' .csv) of the reference ball")
    p.add_argument("--ball-radius", type=float, required=True, help="the ball's radius (mm)")
    p.add_argument("--centre", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                   help="the ball's centre in the object frame (mm)")
    p.add_argument("--tank", help="the tank's identity (default: the tank the scan records, scan.py's +rig.tank)")
    p.add_argument("--params", nargs="+", default=list(DEFAULT_REFERENCE), choices=list(PARAMETERS),
                   help="geometry parameters to estimate")
    p.add_argument("--n", type=int, default=48, help="grid resolution of the final fit check")
    p.add_argument("--height-tolerance", type=float, default=0.5, metavar="MM",
                   help="how well the water line at the stage's zero is known (90%% half-width, mm: the stage's "
                        "zero, a sensor lag's shift)")
    p.add_argument("--position-tolerance", type=float, default=0.5, metavar="MM",
                   help="how well the ball's centre is known along each axis of the object frame (90%% half-width, "
                        "mm: its mounting); a ball mounted higher is a longer pivot, a ball off the spin axis shows "
                        "the spin zero to about this over its distance from the axis")
    p.add_argument("--sensor-lag", type=float, default=0.0, metavar="S",
                   help="the level sensor's time constant (s), undone in every dip and written to the file: never "
                        "estimated, and a lag above about half the time per reading biases the step scale low")
    p.add_argument("--section-tolerance", type=float, default=None, metavar="FRACTION",
                   help="a balance's scan only: how well the tank's free section is known (90%% half-width of its "
                        "relative error: 0.02 for +-2 %%; default the calibrated range +-20 %%), which bounds the "
                        "step scale's interval")
    p.add_argument("--cross-section", type=float, default=None, metavar="MM2",
                   help="the tank's free section (mm^2) when better known than the scan records it; written to the "
                        "file (a balance's rises use it; a level scan's section is estimated from the ball)")
    p.add_argument("--max-residual", type=float, default=0.05,
                   help="refuse when the ball's relative profile residual exceeds this and 1.5 times what the "
                        "readings' own noise gives")
    p.add_argument("--output", type=Path, default=Path("rig_calibration.yaml"), help="calibration file (.yaml/.json)")
    return p.parse_args(argv)


def check_options(args: argparse.Namespace) -> Ball:
    """The reference ball of ``args`` (``--ball-radius``, ``--centre``, mm) after refusing, with a
    ``ValueError`` naming the option, the numbers no calibration can use: a radius or centre not finite and
    positive, an ``--n`` below 4, ``--max-residual`` not above 0, a tolerance negative or NaN, a
    ``--section-tolerance`` outside [0, 1) (2 meant as 2 %), a sensor lag outside [0, 600] s, an unphysical
    ``--cross-section``, an ``--output`` that cannot be written (:func:`check_output`)."""
    if not all(math.isfinite(c) for c in args.centre):
        raise ValueError(f"--centre must be 3 finite coordinates (mm), got {' '.join(f'{c:g}' for c in args.centre)}")
    try:  # the ball's own message: "ball radius must be ...", naming no flag
        ball = Ball(args.ball_radius, center=tuple(args.centre))
    except ValueError as exc:
        raise ValueError(f"--ball-radius {args.ball_radius:g}: {exc}") from None
    if args.n < 4:  # was named after the scan was read, as "grid resolution n", no flag
        raise ValueError(f"--n must be a grid resolution >= 4 (voxels per axis of the final fit check), got {args.n}")
    check_reference_options(args.max_residual, args.height_tolerance, args.position_tolerance, args.section_tolerance)
    if not 0 <= args.sensor_lag <= MAX_SENSOR_LAG_S:  # NaN fails too
        raise ValueError(f"--sensor-lag must be a time constant in [0, {MAX_SENSOR_LAG_S:g}] s, "
                         f"got {args.sensor_lag:g}")
    try:  # an unphysical --cross-section is named before the scan is read (the geometry's message names no flag)
        initial_geometry(args)
    except ValueError as exc:
        raise ValueError(f"--cross-section {args.cross_section:g} (mm^2): {exc}") from None
    check_output(args.output)
    return ball


def check_output(path: Path) -> None:
    """Raise ``ValueError`` when the calibration file ``path`` cannot be written (a folder, or under a file), before
    the scan is read: it was named only once the whole fit had run."""
    if path.is_dir():
        raise ValueError(f"--output {path} is a folder: give the calibration file's name (.yaml or .json)")
    parent = next((p for p in path.parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise ValueError(f"--output {path}: {parent} is a file, not a folder")


def initial_geometry(args: argparse.Namespace) -> RigGeometry:
    """The configured geometry of ``args``: the known sensor lag (s) and, when given, the tank's section (mm^2)."""
    return RigGeometry(sensor_lag_s=args.sensor_lag, cross_section_mm2=args.cross_section)


def main(argv=None) -> int:
    args = parse_args(argv)
    log_warnings_once()  # a warning both logged and warned shows once
    with user_errors():
        ball = check_options(args)  # before the scan is read: a slip in an option is named at once
        raw = read_scan(args.scan)  # a dipnet raw scan (.jsonl) or the authors' CSV
        recorded = scan_tank(raw.header)
        if args.tank and recorded and args.tank != recorded:
            raise ValueError(f"--tank {args.tank!r}: {args.scan} was recorded in tank {recorded!r}")
        tank = args.tank or recorded
        if not tank:
            raise ValueError(f"{args.scan} does not name its tank: pass --tank")
        reach = args.ball_radius + max(abs(c) for c in args.centre)
        grid = Grid(args.n, 3, extent=2.0 * (reach + 10.0))  # the check runs at the calibrated heights
        geometry, report = calibrate_reference(raw, ball, grid, args.params, initial=initial_geometry(args),
                                               max_relative_residual=args.max_residual,
                                               start_height_tolerance_mm=args.height_tolerance,
                                               position_tolerance_mm=args.position_tolerance,
                                               section_tolerance=args.section_tolerance)
        fitted = report.reference_centroid_mm
        notes = f"ball r={args.ball_radius:g} mm, given centre {list(args.centre)} mm" + \
            (f", fitted centre {[round(v, 3) for v in fitted]} mm" if fitted is not None else "") + \
            f", from {args.scan}"
        calibration = to_calibration(geometry, report, raw.header.rig, str(tank), notes=notes)
        kept = keep_previous(args.output)  # an earlier calibration there is renamed, not overwritten
        path = save_calibration(calibration, args.output)
    print(report.table())
    print(f"wrote {path} (rig {raw.header.rig!r}, tank {tank!r})")
    if kept is not None:
        print(f"the file there before kept as {kept}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
