"""Reference-ball calibration: measure a rig's geometry from dips of a ball of known radius.

Real rigs are not the ideal rig: the tilt pivot sits somewhere along the spin axis, the tilt axis is
offset beside it, the angle encoders have zero offsets, the tank's free cross-section is not the drawing's.
Each shifts where a dip starts and how much a level rise means. A ball of known radius fixes them: its
dips must be the profiles of that ball. This script records such a scan on the fake rig with a *wrong*
rig (pivot 20 mm, tilt-axis offset 10 mm, tilt zero 1 deg, a free cross-section of 19,000 mm^2 where the
config says 20,000; the scan is planned for the ideal rig) and a
grid plan of tilts x spins, then estimates the geometry as `scripts/calibrate.py` does and writes the
calibration file. The ball is mounted 25 mm off the spin axis: a centred ball cannot show the spin zero, and
shows the tilt zero only as well as its mounting height and position are known. With hardware the same
steps are
`python scripts/scan.py name=ball orientations=grid 'tilts=[0,25,50,70]' 'spins=[0,90,180,270]' +rig.tank=lab-tank-1`
(a 30 mm ball with its centre at x = 25 mm in the object frame), then
`python scripts/calibrate.py scans/ball/rawscan.jsonl --ball-radius 30 --centre 25 0 0 --output rig_calibration.yaml`;
later scans record the file with `+rig.calibration=rig_calibration.yaml`, readers take it with
`+source.reader.calibration=rig_calibration.yaml`.
"""

import sys
from pathlib import Path

from hydra import compose, initialize_config_module

from dipnet.calibration.model import DEFAULT_REFERENCE, to_calibration
from dipnet.calibration.reference import calibrate_reference
from dipnet.core.calibration_file import save_calibration
from dipnet.core.grid import Grid
from dipnet.core.rawscan import read_rawscan
from dipnet.jobs.scan import scan_from_config
from dipnet.shapes import Ball

out = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/examples/reference_ball")
out.mkdir(parents=True, exist_ok=True)
RADIUS, CENTRE = 30.0, (25.0, 0.0, 0.0)  # mm; the ball off the spin axis

overrides = [
    "rig.fake.shape._target_=dipnet.shapes.Ball", f"rig.fake.shape.radius={RADIUS}",   # the reference ball
    f"+rig.fake.shape.center={list(CENTRE)}", "~rig.fake.shape.name", "~rig.fake.shape.ndim",
    "+rig.fake.geometry={pivot_mm: 20.0, tilt_axis_offset_mm: 10.0, tilt_zero_deg: 1.0, cross_section_mm2: 19000.0}",
    "orientations=grid", "tilts=[0,25,50,70]", "spins=[0,90,180,270]",
    "protocol.stop_mm=100", "protocol.step_mm=1.5", "+rig.tank=lab-tank-1",
    "progress=false", "fsync=false"]
with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
    scan_cfg = compose(config_name="scan", overrides=overrides)
scan_from_config(scan_cfg, out / "ball.jsonl")

raw = read_rawscan(out / "ball.jsonl")
grid = Grid(48, 3, extent=2.0 * (RADIUS + max(CENTRE) + 10.0))   # the fit check's grid, as scripts/calibrate.py builds it
geometry, report = calibrate_reference(raw, Ball(RADIUS, center=CENTRE), grid, DEFAULT_REFERENCE)
calibration = to_calibration(geometry, report, raw.header.rig, "lab-tank-1",
                             notes=f"ball r={RADIUS:g} mm at {list(CENTRE)}")
path = save_calibration(calibration, out / "rig_calibration.yaml")
print(report.table())
print(f"true: pivot 20 mm, tilt-axis offset 10 mm, tilt zero 1 deg, cross-section 19,000 mm^2; wrote {path}")
