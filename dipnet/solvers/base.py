"""The solver interface: ``solve(measurement, operator) -> Reconstruction``.

Solvers never read files or configs; scripts and Hydra build them.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import replace

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.measurement import BEYOND_SLABS_TOL, DipMeasurement
from dipnet.operators.base import DipOperator
from dipnet.core.reconstruction import Reconstruction

#: A slab's noise sigma is taken as at least this share of the median sigma in a data term (no infinite weight).
SIGMA_FLOOR = 1e-3


class Solver(ABC):
    """Reconstructs an occupancy volume from a measurement through a dip operator."""

    name: str = "solver"

    @abstractmethod
    def solve(self, measurement: DipMeasurement, operator: DipOperator) -> Reconstruction:
        """Return the reconstruction on ``operator.grid``."""


def checked_threshold(threshold: float | str, rule: str) -> float | str:
    """A solver's ``threshold`` option: its named ``rule`` (e.g. ``"otsu"``), or an occupancy level in
    ``(0, 1)`` as a float. Anything else raises a ``ValueError``: a level outside ``(0, 1)`` (or NaN) makes the
    binary shape (:attr:`~dipnet.core.reconstruction.Reconstruction.binary`) of an occupancy in ``[0, 1]`` empty
    or the whole grid, beyond the working ball (the same limit as ``check_thresholds`` of a config)."""
    if threshold == rule:
        return rule
    if not is_real(threshold) or not 0 < threshold < 1:
        reason = (f"this solver's only named rule is {rule!r} ('volume' is the optimisation solvers' rule, 'otsu' the "
                  "linear solvers')" if isinstance(threshold, str) else
                  "a level of 1 or above leaves an occupancy in [0, 1] empty, one of 0 or below takes the whole grid")
        raise ValueError(f"threshold must be an occupancy level in (0, 1) or {rule!r}, got {threshold!r}: {reason}")
    return float(threshold)


def checked_temperatures(start: float, end: float) -> tuple[float, float]:
    """A solver's sigmoid temperatures ``(temperature_start, temperature_end)`` as floats: finite numbers with
    ``0 < end <= start``. Anything else raises a ``ValueError`` (an infinite temperature flattens every logit to an
    occupancy of 0.5: a NaN loss once solving)."""
    if not (is_real(start) and is_real(end)) or not 0 < end <= start < math.inf:
        raise ValueError(f"need finite temperatures 0 < temperature_end <= temperature_start, got "
                         f"temperature_start={start!r}, temperature_end={end!r}")
    return float(start), float(end)


def measured_profiles(measurement: DipMeasurement, operator: DipOperator) -> torch.Tensor:
    """The measured slab volumes on the operator's slabs, ``(K, M)`` float64, mm^3.

    The measurement's orientations must be the operator's (same order); its slabs are
    resampled onto :meth:`DipOperator.slab_edges` when thickness or offsets differ, with a warning
    when that drops more than :data:`~dipnet.core.measurement.BEYOND_SLABS_TOL` of a profile's volume.

    Raises:
        TypeError: ``measurement`` is not a :class:`DipMeasurement` (e.g. a profiles tensor, or the two
            arguments swapped) or ``operator`` not a :class:`DipOperator`.
    """
    if not isinstance(measurement, DipMeasurement) or not isinstance(operator, DipOperator):
        hint = ("; profiles on the operator's slabs make one: DipMeasurement(operator.directions, profiles, "
                "operator.slab_thickness, operator.slab_edges()[:1].expand(operator.n_orientations))"
                if isinstance(measurement, (torch.Tensor, np.ndarray)) else "")
        raise TypeError(f"solve(measurement, operator) takes a DipMeasurement and a DipOperator, got "
                        f"{type(measurement).__name__} and {type(operator).__name__}{hint}")
    fix = (f"build the operator from the measurement's own directions on a {measurement.ndim}D grid: "
           "make_operator(grid, measurement.directions)")
    if measurement.n_orientations != operator.n_orientations or measurement.ndim != operator.grid.ndim:
        raise ValueError(
            f"measurement has {measurement.n_orientations} orientations in {measurement.ndim}D, "
            f"the operator {operator.n_orientations} in {operator.grid.ndim}D: {fix}")
    dirs = measurement.directions / measurement.directions.norm(dim=1, keepdim=True)
    if not torch.allclose(dirs, operator.directions.to(dirs), atol=1e-6):
        cosine = (dirs * operator.directions.to(dirs)).sum(1).clamp(-1.0, 1.0)
        rows = torch.nonzero(~torch.isclose(cosine, torch.ones_like(cosine), atol=1e-9)).squeeze(1).tolist()
        angle = float(torch.rad2deg(torch.arccos(cosine[rows[0]]))) if rows else 0.0
        raise ValueError(f"the measurement's orientations differ from the operator's in {len(rows)} of "
                         f"{len(dirs)} rows (first: row {rows[0] if rows else 0}, {angle:.3g} deg apart; the rows must "
                         f"be the same dips in the same order): {fix}")
    edges = operator.slab_edges()
    return measurement.profiles.clone() if _same_slabs(measurement, operator) else \
        measurement.resampled(edges, BEYOND_SLABS_TOL)


def _same_slabs(measurement: DipMeasurement, operator: DipOperator) -> bool:
    """Whether ``measurement``'s slabs are the operator's (count, thickness and offsets to 1e-9)."""
    edges = operator.slab_edges()
    return (measurement.n_slabs == operator.n_slabs
            and abs(measurement.slab_thickness - operator.slab_thickness) < 1e-9 * operator.slab_thickness
            and torch.allclose(measurement.offsets.double(), edges[:1].expand_as(measurement.offsets), atol=1e-9))


def measured_sigma(measurement: DipMeasurement, operator: DipOperator) -> torch.Tensor | None:
    """The measurement's noise sigma on the operator's slabs, ``(K, M)`` float64 mm^3 (``None`` without one): its own
    when the slabs are the operator's, else resampled with the profiles (:meth:`DipMeasurement.resampled_sigma`). Not
    its own whenever the shapes agree: slabs of the same count at other offsets hold other volumes."""
    if measurement.sigma is None or _same_slabs(measurement, operator):
        return measurement.sigma
    return measurement.resampled_sigma(operator.slab_edges())


def noise_sigma(measurement: DipMeasurement, operator: DipOperator) -> tuple[torch.Tensor | None, str]:
    """``(sigma, source)``: the noise sigma the solvers' data term and weight rules take, on the operator's slabs
    (``(K, M)`` float64 mm^3, or ``None``).

    ``source`` is ``"sigma"`` for a stated noise (:func:`measured_sigma`); ``"readings"`` when none is stated but
    preprocessing found the readings' own scatter to hold their noise alone (``metadata["readings_slab_sigma"]``,
    :mod:`dipnet.preprocessing.preprocess`; 0.86-1.30 of the true noise on correct simulations): the same sigma on
    every slab, a slab being the difference of two cumulative readings whatever its width; ``"estimated"`` with
    neither (``None``: the weight rules then estimate it from the profiles, which under-reads at fine slabs).
    """
    sigma = measured_sigma(measurement, operator)
    if sigma is not None:
        return sigma, "sigma"
    reading = measurement.metadata.get("readings_slab_sigma")
    if is_real(reading) and math.isfinite(reading) and reading > 0:
        shape = (operator.n_orientations, operator.n_slabs)
        return torch.full(shape, float(reading), dtype=torch.float64), "readings"
    return None, "estimated"


SMOOTHED_NOISE_MODEL = "independent, the profiles being smoothed (their errors are not the readings' differences)"
"""The noise model a data term records for profiles smoothed in preprocessing, whatever model it was asked for."""


def readings_differenced(measurement: DipMeasurement) -> bool:
    """Whether the profiles' slabs are the differences of cumulative readings as read: ``False`` when they were
    smoothed in preprocessing (``metadata["smoothed"]``), so that their errors are not the readings' differences
    and a noise model of differenced readings (the solvers' ``noise_model="correlated"``, the surface refit's
    ``white_share``) does not hold for them."""
    return not measurement.metadata.get("smoothed", False)


def on_operator_slabs(measurement: DipMeasurement, operator: DipOperator) -> DipMeasurement:
    """``measurement`` with its profiles on the operator's slabs (:func:`measured_profiles`): itself when
    they are there already, else a copy resampled once, its per-slab ``sigma`` with it (:func:`measured_sigma`).
    Solvers that read the profiles at every stage or round call this first, so a volume
    lost beyond the operator's slabs is warned about once per solve."""
    profiles = measured_profiles(measurement, operator)  # checks the rows are the operator's dips
    if _same_slabs(measurement, operator):
        return measurement
    return replace(measurement, profiles=profiles, slab_thickness=operator.slab_thickness,
                   offsets=operator.slab_edges()[:1].to(measurement.offsets).expand(operator.n_orientations).clone(),
                   sigma=measured_sigma(measurement, operator))
