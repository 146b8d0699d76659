"""Training pairs for the learned prior: (cheap reconstruction, true occupancy) of generated shapes.

For each seed, the procedural solid (:mod:`dipnet.shapes.procedural`) is voxelised on the
``n^3`` grid (``fill`` of the working ball, partial volume), its slab volumes along ``dips``
Fibonacci directions are computed with the dip operator, white noise is added to the level
readings (the cumulative profile) at ``snr_db`` for every other seed (odd positions in the list;
``None`` = all clean), and the voxel solver (``solver_options``, default: its defaults with
``iterations`` steps) reconstructs the soft occupancy. Computing the data with the operator on
the voxelised truth is an "inverse crime" that is harmless for training; the benchmark
simulates its test shapes from their surfaces.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.shapes.procedural import generated_occupancy
from dipnet.solvers.voxel import VoxelSolver


def noisy_profiles(profiles: torch.Tensor, snr_db: float | None, generator: torch.Generator) -> torch.Tensor:
    """Profiles ``(K, M)`` (mm^3) with white noise on their running sums at ``snr_db`` (the level
    readings' noise model: ``sigma = rms(cumulative) / 10^(snr/20)``); unchanged when ``None``."""
    if snr_db is None:
        return profiles
    cum = torch.cumsum(profiles, dim=-1)
    sigma = cum.pow(2).mean().sqrt() / 10.0 ** (snr_db / 20.0)
    cum = cum + sigma * torch.randn(cum.shape, generator=generator, dtype=cum.dtype)
    return torch.diff(cum, dim=-1, prepend=torch.zeros_like(cum[..., :1]))


def make_pair(seed: int, n: int = 64, dips: int = 41, snr_db: float | None = None, fill: float = 0.9,
              solver_options: Mapping | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(reconstruction, truth)``, each ``(n, n, n)`` float32 in ``[0, 1]``, for one generated shape."""
    grid = Grid(n, 3)
    truth = torch.from_numpy(generated_occupancy(seed, grid, fill=fill)).double()
    operator = make_operator(grid, fibonacci_hemisphere(dips), n)
    with torch.no_grad():
        profiles = noisy_profiles(operator(truth), snr_db, torch.Generator().manual_seed(int(seed)))
    k = operator.n_orientations
    measurement = DipMeasurement(operator.directions, profiles, operator.slab_thickness,
                                 operator.slab_edges()[:1].expand(k))
    options = {"progress": False, "seed": int(seed), **dict(solver_options or {})}
    recon = VoxelSolver(**options).solve(measurement, operator)
    return recon.occupancy.numpy().astype(np.float32), truth.numpy().astype(np.float32)


def pairs_key(seeds: Sequence[int], **options) -> str:
    """A short digest of what makes a set of pairs (seeds and options)."""
    text = json.dumps({"seeds": [int(s) for s in seeds], **options}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def build_pairs(seeds: Sequence[int], cache: Path | None = None, n: int = 64, dips: int = 41,
                snr_db: float | None = 30.0, fill: float = 0.9, solver_options: Mapping | None = None,
                progress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Pairs for every seed (odd positions noisy at ``snr_db``), ``(S, n, n, n)`` inputs and targets,
    each pair cached as ``cache/pair_<seed>_<digest>.npz`` so an interrupted build resumes."""
    options = {"n": n, "dips": dips, "fill": fill, "solver_options": dict(solver_options or {})}
    inputs, targets = [], []
    for i, seed in enumerate(tqdm(list(seeds), desc="training pairs", disable=not progress)):
        snr = snr_db if i % 2 else None
        file = None if cache is None else Path(cache) / f"pair_{seed}_{pairs_key([seed], snr_db=snr, **options)}.npz"
        if file is not None and file.is_file():
            with np.load(file) as saved:
                x, y = saved["input"], saved["target"]
        else:
            x, y = make_pair(int(seed), snr_db=snr, **options)
            if file is not None:
                file.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(file, input=x, target=y)
        inputs.append(x)
        targets.append(y)
    return np.stack(inputs), np.stack(targets)
