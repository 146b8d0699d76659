"""Training pairs for the learned prior: (voxel reconstruction, true occupancy) of generated shapes.

For each seed and each noise level, the procedural solid (:mod:`dipnet.shapes.procedural`, its
farthest point at ``fill`` of the working ball) is dipped along ``dips`` Fibonacci directions by
the simulator with the benchmark's level sensor (:func:`dipnet.simulator.simulate.simulate_measurement`,
exact readings when noise-free, white noise at ``snr_db`` otherwise, both with ``quantum_mm=0``),
and the voxel solver (its defaults, so the data-chosen TV weight; ``solver_options`` override)
reconstructs the soft occupancy on the ``n^3`` grid. The target is the solid's partial-volume
occupancy (3^3 supersamples per voxel). The inputs are therefore what the solver really returns
on the benchmark's data, noise-free and noisy, not a cheaper stand-in.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.shapes.procedural import generated_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.voxel import VoxelSolver


def make_pair(seed: int, n: int = 64, dips: int = 41, snr_db: float | None = None, fill: float = 0.9,
              solver_options: Mapping | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(reconstruction, truth)``, each ``(n, n, n)`` float32 in ``[0, 1]``, for one generated shape
    dipped ``dips`` times, noise-free (``snr_db=None``) or with level-sensor noise at ``snr_db`` dB."""
    grid = Grid(n, 3)
    shape = generated_shape(int(seed), radius=fill * grid.radius)
    sensor = LevelSensor(snr_db=snr_db, quantum_mm=0.0, seed=int(seed))
    _, measurement = simulate_measurement(shape, fibonacci_hemisphere(dips), grid=grid, sensor=sensor,
                                          seed=int(seed), progress=False)
    operator = make_operator(grid, measurement.directions, n)
    options = {"progress": False, "seed": int(seed), **dict(solver_options or {})}
    recon = VoxelSolver(**options).solve(measurement, operator)
    truth = shape.occupancy(grid, supersample=3)
    return recon.occupancy.numpy().astype(np.float32), np.asarray(truth, dtype=np.float32)


def pairs_key(seeds: Sequence[int], **options) -> str:
    """A short digest of what makes a set of pairs (seeds and options)."""
    text = json.dumps({"seeds": [int(s) for s in seeds], **options}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def build_pairs(seeds: Sequence[int], cache: Path | None = None, n: int = 64, dips: int = 41,
                noise_levels: Sequence[float | None] = (None, 30.0), fill: float = 0.9,
                solver_options: Mapping | None = None, progress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """One pair per seed and noise level (``None`` = noise-free, else SNR in dB), stacked as
    ``(S * len(noise_levels), n, n, n)`` inputs and targets (seed-major). Each pair is cached as
    ``cache/pair_<seed>_<digest>.npz``, so an interrupted build resumes and several processes can
    fill one cache (each with its own seeds)."""
    options = {"n": n, "dips": dips, "fill": fill, "solver_options": dict(solver_options or {}),
               "recipe": "simulated-2"}
    jobs = [(int(seed), snr) for seed in seeds for snr in noise_levels]
    inputs, targets = [], []
    for seed, snr in tqdm(jobs, desc="training pairs", disable=not progress):
        file = None if cache is None else Path(cache) / f"pair_{seed}_{pairs_key([seed], snr_db=snr, **options)}.npz"
        if file is not None and file.is_file():
            with np.load(file) as saved:
                x, y = saved["input"], saved["target"]
        else:
            x, y = make_pair(seed, snr_db=snr, n=n, dips=dips, fill=fill, solver_options=solver_options)
            if file is not None:
                file.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(file, input=x, target=y)
        inputs.append(x)
        targets.append(y)
    return np.stack(inputs), np.stack(targets)
