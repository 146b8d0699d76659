"""The uncertainty maps of a run, into the run directory: added to ``reconstruction.npz``, and a figure."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.uncertainty import calibration_by_decile, uncertainty
from dipnet.operators import DipOperator
from dipnet.outputs.plots import mid_slices, plt, save_figure, show_slice

log = logging.getLogger(__name__)


def write_uncertainty(out: Path, reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator,
                      truth: np.ndarray | None = None, figure: bool = True) -> dict[str, Any]:
    """Add the maps ``uncertainty_std`` / ``uncertainty_p_wrong`` to ``out/reconstruction.npz``,
    draw ``out/uncertainty.png`` and return the summary metrics (with the error rate per
    uncertainty decile when the true occupancy ``truth`` is known)."""
    maps, summary = uncertainty(reconstruction, measurement, operator)
    reconstruction.save(out / "reconstruction.npz", uncertainty_std=maps["std"], uncertainty_p_wrong=maps["p_wrong"])
    scores: dict[str, Any] = dict(summary)
    if truth is not None:
        deciles = calibration_by_decile(maps["p_wrong"], reconstruction.binary, np.asarray(truth) > 0.5)
        scores["error_rate_by_uncertainty_decile"] = [round(float(v), 5) for v in deciles]
        if not deciles[-1] > deciles[0]:
            message = (f"uncertainty is not calibrated on this run: error rate {deciles[-1]:.3f} in the most "
                       f"uncertain decile vs {deciles[0]:.3f} in the least")
            log.warning(message)
            warnings.warn(message, stacklevel=2)
    if figure:
        plot_uncertainty(reconstruction.binary, maps, out / "uncertainty.png", reconstruction.grid.extent)
    return scores


def plot_uncertainty(binary: np.ndarray, maps: dict[str, np.ndarray], path: Path, extent_mm: float | None = None) -> Path:
    """Mid-plane cuts of the binary reconstruction, the posterior std and ``p_wrong`` (one row
    per axis), on mm axes when the grid side ``extent_mm`` is given."""
    columns = [("reconstruction", np.asarray(binary, float), "gray", 1.0),
               ("posterior std", maps["std"], "magma", float(maps["std"].max())),
               ("P(binary call wrong)", maps["p_wrong"], "magma", 0.5)]
    slices = [mid_slices(volume, extent_mm) for _, volume, _, _ in columns]
    fig, axes = plt.subplots(len(slices[0]), 3, figsize=(11, 3.4 * len(slices[0])), squeeze=False,
                             layout="constrained")
    for r, row in enumerate(axes):
        for c, (ax, (label, _, cmap, vmax)) in enumerate(zip(row, columns)):
            im = show_slice(ax, slices[c][r], extent_mm, label, cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-9))
            fig.colorbar(im, ax=ax, fraction=0.046)
    return save_figure(fig, path)
