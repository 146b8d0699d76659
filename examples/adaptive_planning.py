"""Adaptive planning: choose each batch of dips where the current reconstruction is least sure.

Each dip costs minutes of robot time, so dipnet can plan them: start from a few dips spread over the reach,
reconstruct, fit a posterior around the reconstruction (per voxel: the probability that its inside/outside
call is wrong), pick the next batch of dips whose profiles would tell the most, dip, and repeat until the
budget is spent. Here on the simulated chamber box with level-sensor noise at 30 dB, 8 initial dips and
batches of 4 up to 20 dips, with the `voxel` solver (the planner needs a reconstruction whose misfit is
the noise, not model error) at 24^3. The bigger run:
`python scripts/reconstruct.py planner=adaptive planner.budget=41 solver=voxel snr_db=30`; within the
authors' 0-35 deg tilt limit add `reach=authors_rig`.
"""

import sys
from pathlib import Path

from hydra import compose, initialize_config_module

from dipnet.jobs.pipeline import run

out = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/examples/adaptive_planning")

overrides = ["planner=adaptive", "planner.budget=20", "planner.initial_dips=8", "planner.batch_size=4",
             "planner.planner.resolution=16", "solver=voxel", "snr_db=30", "resolution=24",
             "output.progress=false"]
with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
    cfg = compose(config_name="config", overrides=overrides)
result = run(cfg, out)

m = result.metrics
print(f"{m['n_dips']} dips: IoU {m['iou']:.3f}, Chamfer {m['chamfer']:.4f}; "
      f"expected misclassified fraction {m['expected_error_fraction']:.4f}")
print("files:", ", ".join(sorted(p.name for p in out.iterdir() if not p.name.startswith("."))))
