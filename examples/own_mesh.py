"""Your own mesh: reconstruct a part from an STL file in its own units.

Any PLY, STL, OBJ, OFF or GLB mesh can be dipped; give it in mm, or scale it with `shape.scale` (a factor
to mm) or `shape.radius` (scale to this radius in mm). Here the part is made with trimesh (a ring, 8 cm
across, saved in centimetres) so the script needs no file; the job is the command-line pipeline,
`python scripts/reconstruct.py shape=mesh shape.path=part_cm.stl shape.scale=10 resolution=24 n_dips=60`,
composed from the same Hydra configs in Python. The run directory gets the meshes, `metrics.json`,
the measurement and the figures (`mesh.png`, `slices.png`, ...).
"""

import sys
from pathlib import Path

import trimesh
from hydra import compose, initialize_config_module

from dipnet.jobs.pipeline import run

out = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/examples/own_mesh")
out.mkdir(parents=True, exist_ok=True)

ring = trimesh.creation.annulus(r_min=2.0, r_max=4.0, height=2.5)   # cm: 8 cm across, 2.5 cm high
ring.export(out / "part_cm.stl")

overrides = ["shape=mesh", f"shape.path={out / 'part_cm.stl'}", "shape.scale=10",   # cm -> mm
             "resolution=24", "n_dips=60", "output.progress=false", "output.uncertainty=false"]
with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
    cfg = compose(config_name="config", overrides=overrides)
result = run(cfg, out / "run")

m = result.metrics
print(f"ring of {ring.volume * 1000:,.0f} mm^3: IoU {m['iou']:.3f}, Chamfer {m['chamfer']:.4f} "
      f"(of the bounding-box diagonal), volume error {m['volume_error']:+.3f}")
# the meshes are in mm; metrics.json's frame_scale (mm per unit of the file) takes them back to the file's cm
back = trimesh.load(out / "run" / "reconstruction.ply").apply_scale(1 / m["frame_scale"])
print(f"reconstruction.ply / frame_scale {m['frame_scale']:g}: x {back.bounds[0, 0]:.2f} to {back.bounds[1, 0]:.2f} cm "
      f"(the part's file: {ring.bounds[0, 0]:.2f} to {ring.bounds[1, 0]:.2f} cm)")
# the outputs; not the hidden, empty .rawscan.jsonl.lock the scan writer locks (it stays by design: dipnet/core/locks.py)
print("files:", ", ".join(sorted(p.name for p in (out / "run").iterdir() if not p.name.startswith("."))))
