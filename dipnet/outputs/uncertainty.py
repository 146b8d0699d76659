"""The uncertainty maps of a run, into the run directory: added to ``reconstruction.npz``, and a figure."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.core.warn import log_and_warn
from dipnet.evaluation.ensemble import brier_score, ensemble_uncertainty, occupancy_probability
from dipnet.evaluation.uncertainty import SURE_P_WRONG, calibration_by_decile, sure_error_rate, uncertainty
from dipnet.operators import DipOperator
from dipnet.solvers.base import Solver
from dipnet.outputs.plots import mid_slices, plt, save_figure, show_slice

log = logging.getLogger(__name__)

#: ``output.uncertainty`` values: the linearised Gaussian posterior (``true`` is the same) or an ensemble
#: of reconstructions from perturbed data (:mod:`dipnet.evaluation.ensemble`).
METHODS = ("linearised", "samples")
#: wrong voxels among those the map calls sure below which a high error rate there is not reported (one wrong voxel
#: among ten sure ones is chance, not a map that is certain where the shape is wrong)
SURE_WRONG_MIN = 3


def write_uncertainty(out: Path, reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator,
                      truth: np.ndarray | None = None, figure: bool = True, method: str = "linearised",
                      solver: Solver | None = None, n_samples: int = 4, seed: int = 0,
                      iterations_scale: float = 1.0) -> dict[str, Any]:
    """Add the maps ``uncertainty_std`` / ``uncertainty_p_wrong`` (and with ``method="samples"``
    ``uncertainty_probability``, the ensemble's occupancy probability) to ``out/reconstruction.npz``,
    draw ``out/uncertainty.png`` and return the summary metrics (with the error rate per
    uncertainty decile, the error rate of the voxels it calls sure, ``error_rate_where_sure``, and the Brier score of
    the occupancy probability when the truth is known; a warning when either says the map is not calibrated).
    ``truth`` ``grid.shape``: the true inside / outside (bool; a job gives the reference of its IoU and false rates,
    ``truth_occupancy > metrics.reference_level(...)``), or a true occupancy in [0, 1], whose voxels above 0.5 are
    taken for inside (at 24^3 the chamber box's are 15 % more than its exact volume, the reference's 5.6 %).
    ``method="samples"`` re-runs ``solver`` ``n_samples`` times (seeded by ``seed``), each with ``iterations_scale``
    of its iterations."""
    if method not in METHODS:
        raise ValueError(f"unknown uncertainty method {method!r}; choose one of {METHODS}")
    extra: dict[str, np.ndarray] = {}
    if method == "samples":
        if solver is None:
            raise ValueError("uncertainty method 'samples' needs the solver that made the reconstruction")
        maps, summary = ensemble_uncertainty(reconstruction, measurement, operator, solver, n_samples=n_samples,
                                             seed=seed, iterations_scale=iterations_scale)
        extra["uncertainty_probability"] = maps["probability"]
        probability = maps["probability"]
    else:
        maps, summary = uncertainty(reconstruction, measurement, operator)
        probability = occupancy_probability(maps["p_wrong"], reconstruction.binary)
    reconstruction.save(out / "reconstruction.npz", uncertainty_std=maps["std"], uncertainty_p_wrong=maps["p_wrong"],
                        **extra)
    scores: dict[str, Any] = {"uncertainty_method": method, **summary}
    if truth is not None:
        inside = np.asarray(truth) > 0.5
        deciles = calibration_by_decile(maps["p_wrong"], reconstruction.binary, inside)
        scores["error_rate_by_uncertainty_decile"] = [round(float(v), 5) for v in deciles]
        scores["uncertainty_brier"] = brier_score(probability, reconstruction.binary, inside)
        sure_rate, n_sure, n_sure_wrong = sure_error_rate(maps["p_wrong"], reconstruction.binary, inside)
        scores["error_rate_where_sure"] = None if np.isnan(sure_rate) else sure_rate
        if n_sure_wrong >= SURE_WRONG_MIN and sure_rate > SURE_P_WRONG and reconstruction.binary.any():
            message = (f"uncertainty is confidently wrong on this run: {n_sure_wrong} of the {n_sure} voxels it calls "
                       f"sure (p_wrong < {SURE_P_WRONG:g}) are wrong (error rate {sure_rate:.3f}): the shape is wrong "
                       f"where the map is certain, e.g. parts the reconstruction misses far from its boundary (a "
                       f"missing cone, too few dips); judge this run by its consistency and resolvability, not its "
                       f"uncertainty")
            log_and_warn(log, message, stacklevel=2)
        # no wrong call or voxel: nothing to calibrate; an empty reconstruction calls every true voxel wrong, so its
        # deciles all read 1 whatever the uncertainty (the job said it is empty)
        if np.any(deciles > 0) and not deciles[-1] > deciles[0] and reconstruction.binary.any():
            message = (f"uncertainty is not calibrated on this run: error rate {deciles[-1]:.3f} in the most "
                       f"uncertain decile vs {deciles[0]:.3f} in the least")
            log_and_warn(log, message, stacklevel=2)
    if figure:
        plot_uncertainty(reconstruction.binary, maps, out / "uncertainty.png", reconstruction.grid.extent,
                         std_label="ensemble std" if method == "samples" else "posterior std")
    return scores


def plot_uncertainty(binary: np.ndarray, maps: dict[str, np.ndarray], path: Path, extent_mm: float | None = None,
                     std_label: str = "posterior std") -> Path:
    """Mid-plane cuts of the binary reconstruction, the std map (titled ``std_label``) and ``p_wrong``
    (one row per axis), on mm axes when the grid side ``extent_mm`` is given."""
    columns = [("reconstruction", np.asarray(binary, float), "gray", 1.0),
               (std_label, maps["std"], "magma", float(maps["std"].max())),
               ("P(binary call wrong)", maps["p_wrong"], "magma", 0.5)]
    slices = [mid_slices(volume, extent_mm) for _, volume, _, _ in columns]
    fig, axes = plt.subplots(len(slices[0]), 3, figsize=(11, 3.4 * len(slices[0])), squeeze=False,
                             layout="constrained")
    for r, row in enumerate(axes):
        for c, (ax, (label, _, cmap, vmax)) in enumerate(zip(row, columns)):
            im = show_slice(ax, slices[c][r], extent_mm, label, cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-9))
            fig.colorbar(im, ax=ax, fraction=0.046)
    return save_figure(fig, path)
