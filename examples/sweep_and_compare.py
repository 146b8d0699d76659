"""A sweep and its comparison: run a grid of jobs with Hydra's `-m`, then tabulate and plot them.

Every reconstruction job writes its config, `metrics.json` and volumes into its own folder, so a sweep is
one command and `scripts/compare.py` reads the folder afterwards: `runs.csv` (every job, failed ones
included), `summary.md` / `summary.csv` (mean and std per solver x dips x SNR), `vs_dips.png` and
`montage.png`. This script sweeps two solvers x two dip budgets on a small grid (4 jobs, a few seconds
each) by running the same commands a user types:
`python scripts/reconstruct.py -m solver=minnorm,voxel n_dips=20,60 resolution=16 hydra.sweep.dir=sweeps/mine`
then `python scripts/compare.py sweeps/mine`.
"""

import subprocess
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
out = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/examples/sweep_and_compare")
sweep = out / "sweep"

subprocess.run([sys.executable, str(SCRIPTS / "reconstruct.py"), "-m", "solver=minnorm,voxel", "n_dips=20,60",
                "resolution=16", "output.figures=false", "output.uncertainty=false", "output.resolvability=false",
                "output.progress=false", f"hydra.sweep.dir={sweep}"], check=True)
subprocess.run([sys.executable, str(SCRIPTS / "compare.py"), str(sweep)], check=True)   # prints summary.md

print("comparison files:", ", ".join(sorted(p.name for p in (sweep / "compare").iterdir())))
