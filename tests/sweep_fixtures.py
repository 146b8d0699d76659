"""Fake reconstruction jobs with the files of dipnet.jobs.pipeline's contract, for the sweep tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from dipnet.outputs import export
from dipnet.shapes.isosurface import volume_to_mesh
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import make_directions
from dipnet.core.reconstruction import Reconstruction


def ball(grid: Grid, radius_mm: float) -> np.ndarray:
    """Boolean ball (disk in 2D) of ``radius_mm`` centred on the origin, ``grid.shape``."""
    r = grid.centers().reshape(-1, grid.ndim).norm(dim=1).reshape(grid.shape)
    return (r <= radius_mm).numpy()


def write_job(job: Path, *, solver: str, n_dips: int, snr_db: float | None, seed: int, metrics: dict | None,
              ndim: int = 2, resolution: int = 16, error: str | None = None, shape: str = "disk") -> Path:
    """One job directory: ``.hydra/{config,overrides,hydra}.yaml`` always; ``metrics.json``,
    ``reconstruction.npz``, ``measurement.npz`` (and ``truth.ply``/``reconstruction.ply`` in 3D)
    when ``metrics`` is given; ``error.txt`` when ``error`` is given."""
    grid = Grid(resolution, ndim, 100.0)
    cfg = {"ndim": ndim, "resolution": resolution, "n_dips": n_dips, "n_slabs": None, "seed": seed,
           "snr_db": snr_db, "extent_mm": 100.0, "shape": {"_target_": "dipnet.shapes.builtin_shape", "name": shape},
           "solver": {"_target_": "dipnet.solvers.MinNormSolver", "method": solver},
           "source": {"kind": "simulated", "simulator": {"sensor": {"snr_db": "${snr_db}"}}},
           "operator": {"_target_": "dipnet.operators.make_operator", "backend": "auto"}}
    overrides = [f"solver={solver}", f"n_dips={n_dips}", f"seed={seed}"]
    hydra = {"hydra": {"runtime": {"choices": {"solver": solver, "shape": "builtin"}}}}
    (job / ".hydra").mkdir(parents=True)
    for name, data in (("config", cfg), ("overrides", overrides), ("hydra", hydra)):
        OmegaConf.save(OmegaConf.create(data), job / ".hydra" / f"{name}.yaml")
    if metrics is not None:
        radius = 30.0 * (1 - 1 / n_dips)
        truth, recon = ball(grid, 30.0), ball(grid, radius)
        occupancy = torch.as_tensor(recon, dtype=torch.float32)
        Reconstruction(occupancy, grid, threshold=0.5).save(job / "reconstruction.npz")
        directions = make_directions("fibonacci" if ndim == 3 else "uniform", n_dips, ndim, seed)
        profiles = torch.rand(n_dips, resolution, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
        DipMeasurement(directions, profiles, 100.0 / resolution, torch.full((n_dips,), -50.0)).save(job / "measurement.npz")
        if ndim == 3:
            export.save_mesh(volume_to_mesh(truth.astype(np.float32), grid, 0.5), job / "truth.ply")
            export.save_mesh(volume_to_mesh(recon.astype(np.float32), grid, 0.5), job / "reconstruction.ply")
        full = {"solver": solver, "seconds": 0.1, "n_dips": n_dips, "resolution": resolution, "ndim": ndim,
                "measured_volume_mm3": 1.0, "reconstructed_volume_mm3": 1.0, "shape": shape, "snr_db": snr_db,
                **metrics}
        (job / "metrics.json").write_text(json.dumps(full))
    if error is not None:
        (job / "error.txt").write_text(f"{error}\n\nTraceback (most recent call last): ...\n")
    return job
