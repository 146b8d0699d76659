"""Fake reconstruction jobs with the files of dipnet.jobs.pipeline's contract, for the sweep tests: one job
(:func:`write_job`) or a whole sweep whose metrics follow known formulas (:func:`write_sweep`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import make_directions
from dipnet.core.reconstruction import Reconstruction
from dipnet.outputs import export
from dipnet.shapes.isosurface import volume_to_mesh

#: The metrics of a typical run (every group, and one key no group knows).
METRICS = {"iou": 0.9687, "chamfer": 0.004018, "profile_residual": 0.0588, "profile_residual_expected": 0.0226,
           "volume_ratio": 1.059, "consistency": "inconsistent", "uncertain_fraction": 0.2624,
           "expected_error_fraction": 0.3087, "seconds": 12.05, "validation": {"readings_repaired": 0},
           "error_rate_by_uncertainty_decile": [0.0] * 9 + [0.24], "some_new_metric": 1.5}


def ball(grid: Grid, radius_mm: float) -> np.ndarray:
    """Boolean ball (disk in 2D) of ``radius_mm`` centred on the origin, ``grid.shape``."""
    r = grid.centers().reshape(-1, grid.ndim).norm(dim=1).reshape(grid.shape)
    return (r <= radius_mm).numpy()


def write_job(job: Path, *, solver: str, n_dips: int, snr_db: float | None, seed: int, metrics: dict | None,
              ndim: int = 2, resolution: int = 16, error: str | None = None, shape: str = "disk",
              recording: str | None = None, history: dict[str, list[float]] | None = None) -> Path:
    """One job directory: ``.hydra/{config,overrides,hydra}.yaml`` always; ``metrics.json``,
    ``reconstruction.npz``, ``measurement.npz`` (and ``truth.ply``/``reconstruction.ply`` in 3D)
    when ``metrics`` is given; ``error.txt`` when ``error`` is given. ``recording``: the job read
    that file (a recorded source: the configured ``shape`` is unused and not in the metrics). ``history``: the
    solver's loss terms per iteration, kept in the reconstruction and written to ``history.json``."""
    grid = Grid(resolution, ndim, 100.0)
    cfg = {"ndim": ndim, "resolution": resolution, "n_dips": n_dips, "n_slabs": None, "seed": seed,
           "snr_db": snr_db, "extent_mm": 100.0, "shape": {"_target_": "dipnet.shapes.builtin_shape", "name": shape},
           "solver": {"_target_": "dipnet.solvers.MinNormSolver", "method": solver},
           "source": {"kind": "simulated", "simulator": {"sensor": {"snr_db": "${snr_db}"}}} if recording is None
           else {"_target_": "dipnet.preprocessing.sources.RecordedSource", "reader": {"path": recording}},
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
        Reconstruction(occupancy, grid, threshold=0.5, history=history or {}).save(job / "reconstruction.npz")
        if history:
            (job / "history.json").write_text(json.dumps(history))
        directions = make_directions("fibonacci" if ndim == 3 else "uniform", n_dips, ndim, seed)
        profiles = torch.rand(n_dips, resolution, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
        DipMeasurement(directions, profiles, 100.0 / resolution,
                       torch.full((n_dips,), -50.0)).save(job / "measurement.npz")
        if ndim == 3:
            export.save_mesh(volume_to_mesh(truth.astype(np.float32), grid, 0.5), job / "truth.ply")
            export.save_mesh(volume_to_mesh(recon.astype(np.float32), grid, 0.5), job / "reconstruction.ply")
        full = {"solver": solver, "seconds": 0.1, "n_dips": n_dips, "resolution": resolution, "ndim": ndim,
                "measured_volume_mm3": 1.0, "reconstructed_volume_mm3": 1.0, "snr_db": snr_db,
                **({"shape": shape} if recording is None else {}), **metrics}
        (job / "metrics.json").write_text(json.dumps(full))
    if error is not None:
        (job / "error.txt").write_text(f"{error}\n\nTraceback (most recent call last): ...\n")
    return job


SOLVERS, DIPS, SEEDS, SNRS = ("minnorm", "lsmr"), (4, 8, 16), (0, 1), (10.0, 20.0, 30.0)


def iou_of(solver: str, n_dips: int, seed: int) -> float:
    return 1 - 1 / n_dips - 0.01 * seed + (0.02 if solver == "lsmr" else 0.0)


def chamfer_of(n_dips: int, seed: int) -> float:
    return 0.1 / n_dips + 0.001 * seed


def write_sweep(root: Path) -> Path:
    """12 noise-free jobs (2 solvers x 3 budgets x 2 seeds), 3 noisy ones, a failed one, a
    partial one (config only) and an empty numbered directory, in ``root``."""
    (root / "multirun.yaml").write_text("hydra: {}\n")
    num = 0
    for solver in SOLVERS:
        for n in DIPS:
            for seed in SEEDS:
                write_job(root / str(num), solver=solver, n_dips=n, snr_db=None, seed=seed,
                          metrics={"iou": iou_of(solver, n, seed), "chamfer": chamfer_of(n, seed),
                                   "false_positive": 0.0, "false_negative": 0.0})
                num += 1
    for snr in SNRS:
        write_job(root / str(num), solver="minnorm", n_dips=8, snr_db=snr, seed=0,
                  metrics={"iou": iou_of("minnorm", 8, 0) - 1 / snr, "chamfer": chamfer_of(8, 0),
                           "false_positive": 1 / snr, "false_negative": 0.5 / snr})
        num += 1
    write_job(root / str(num), solver="lsmr", n_dips=32, snr_db=None, seed=0, metrics=None,
              error="ValueError: n_dips too large for the test")
    write_job(root / str(num + 1), solver="lsmr", n_dips=64, snr_db=None, seed=0, metrics=None)
    (root / str(num + 2)).mkdir()
    return root


def is_png(path: Path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
