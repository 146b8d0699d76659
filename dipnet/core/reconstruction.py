"""Reconstruction: what every solver returns."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.grid import Grid, as_grid

if TYPE_CHECKING:
    import trimesh


@dataclass
class Reconstruction:
    """A solver's result on a grid.

    Attributes:
        occupancy: estimated occupancy on ``grid``, ``grid.shape``, a float tensor (a numpy array is converted):
            probabilities in ``[0, 1]`` for the optimisation solvers, raw least-squares values for ``minnorm``.
        grid: the grid.
        threshold: the level that separates inside from outside (e.g. Otsu's).
        history: loss terms per iteration, ``{name: [values]}`` (empty for direct solvers).
        info: solver name, wall time (s), iterations and other facts, JSON-serialisable.
        fine: optionally the same result sampled on a finer grid (implicit solver's
            ``output_upsample``), else ``None``.
        mesh: optionally the result's surface refitted to the dips (:mod:`dipnet.solvers.surface_refit`), a
            watertight ``trimesh.Trimesh`` in mm in the grid's frame; when set it is the result's surface: the one
            a job exports and :func:`~dipnet.evaluation.metrics.evaluate` scores. ``None``: the surface is
            ``occupancy == threshold``.
    """

    occupancy: torch.Tensor
    grid: Grid
    threshold: float = 0.5
    history: dict[str, list[float]] = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    fine: "Reconstruction | None" = None
    mesh: "trimesh.Trimesh | None" = None

    def __post_init__(self) -> None:
        """Raises ``TypeError`` for a ``grid`` that is no :class:`Grid` and ``ValueError`` for an occupancy not of
        ``grid.shape`` or a NaN (or non-numeric) threshold: each gave a result made by hand a wrong meaning, or a
        torch size mismatch deep in :func:`~dipnet.evaluation.consistency.check_consistency`, or an empty
        :attr:`binary` (``x > NaN`` is never true)."""
        self.grid = as_grid(self.grid)
        if not isinstance(self.occupancy, torch.Tensor):  # a numpy array (a result made by hand) is taken as a tensor
            self.occupancy = torch.as_tensor(self.occupancy)
        if tuple(self.occupancy.shape) != self.grid.shape:
            raise ValueError(f"occupancy has shape {tuple(self.occupancy.shape)}, but {self.grid} holds "
                             f"{self.grid.shape}: give the reconstruction the grid its volume was solved on")
        if not is_real(self.threshold) \
                or math.isnan(self.threshold):
            raise ValueError(f"threshold must be a number (the occupancy level between inside and outside), got "
                             f"{self.threshold!r}: with NaN nothing is inside")

    @property
    def binary(self) -> np.ndarray:
        """Boolean volume ``occupancy > threshold``, ``grid.shape``."""
        return (self.occupancy.detach().cpu().numpy() > self.threshold)

    def save(self, path, **extra: np.ndarray) -> None:
        """Write occupancy, binary volume, grid metadata and any ``extra`` named arrays (e.g. the
        uncertainty maps of :func:`dipnet.outputs.uncertainty.write_uncertainty`) to an ``.npz`` file.
        ``history_steps`` records how many iterations the loss history holds (0 for a direct solver), so a
        ``history.json`` an earlier run left beside it is not taken for this one's."""
        steps = max((len(v) for v in self.history.values()), default=0)
        np.savez_compressed(path, **extra, occupancy=self.occupancy.detach().cpu().numpy().astype(np.float32),
                            binary=self.binary, threshold=self.threshold, history_steps=steps,
                            grid_n=self.grid.n, grid_ndim=self.grid.ndim, grid_extent=self.grid.extent,
                            axis_order="zyx" if self.grid.ndim == 3 else "yx")
