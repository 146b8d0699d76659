"""Fake-rig scan and reconstruction: drive the built-in fake rig, then reconstruct from the raw scan.

`scripts/scan.py` drives a motion controller (GRBL or Marlin) and a sensor over pyserial and appends
every reading to `rawscan.jsonl` as it is taken. Without hardware it talks to the *fake rig*
(`conf/rig/fake_grbl.yaml`): a simulated tank with a torus of radius 40 mm, behind `fakerig://` URLs,
speaking the real GRBL protocol. This script runs a short scan (12 Fibonacci orientations instead of 40),
then reconstructs the recording with the `voxel` solver. A fake-rig scan records the object it dipped, so
the reconstruction is scored against it as a simulated one would be. The commands:
`python scripts/scan.py n_dips=12` and
`python scripts/reconstruct.py source=recorded source.reader.path=scans/demo/rawscan.jsonl solver=voxel`.
Running the same scan command again resumes after the last complete orientation.
"""

import sys
from pathlib import Path

from hydra import compose, initialize_config_module

from dipnet.jobs.pipeline import run
from dipnet.jobs.scan import scan_from_config

out = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/examples/fake_rig_scan")
out.mkdir(parents=True, exist_ok=True)
scan_file = out / "rawscan.jsonl"

with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
    scan_cfg = compose(config_name="scan", overrides=["n_dips=12", "progress=false", "fsync=false"])
    scan = scan_from_config(scan_cfg, scan_file)
    print(f"scanned {len(scan.completed())} orientations, "
          f"{sum(o.n_readings for o in scan.orientations)} readings into {scan_file}")
    cfg = compose(config_name="config", overrides=[
        "source=recorded", f"source.reader.path={scan_file}", "solver=voxel", "resolution=24",
        "output.progress=false", "output.uncertainty=false"])
result = run(cfg, out / "reconstruction")

m = result.metrics
print(f"reconstructed {m['reconstructed_volume_mm3']:,.0f} mm^3 of the {m['measured_volume_mm3']:,.0f} mm^3 "
      f"the dips measure: {m['consistency']}")
print(f"against the fake rig's {m['shape']} (a fake-rig scan names its object): IoU {m['iou']:.3f}")
