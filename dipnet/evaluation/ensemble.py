"""Per-voxel probability of occupancy from an ensemble of reconstructions that all fit the data.

Each member re-runs the job's own solver on the measured slab volumes perturbed by a fresh draw of
the noise (randomise-then-optimise, "perturb-and-MAP"): ``g_s = g + e_s``, ``e_s ~ N(0, sigma^2)``,
with ``sigma^2`` the same noise level as the linearised posterior's (:func:`dipnet.evaluation.uncertainty.
misfit_variance`: the binary reconstruction's mean squared misfit, or the measurement's stated
noise if larger). Members of the optimisation solvers also start from their own random occupancy
(:class:`RandomStart`; a smooth random field around the measured volume fraction) and use their own
seed, so the ensemble explores both what the noise leaves open and which local optimum a
non-convex solver reaches. For a linear solver and a quadratic prior this is exact posterior
sampling; for the others it is an approximation whose calibration is measured
(``scripts/bench_uncertainty.py``, ``docs/benchmarks/uncertainty.md``).

Per voxel (reconstruction grid):

* ``probability``: the ensemble's occupancy probability, the mean over members of their occupancy
  mapped through their threshold (:func:`centred_occupancy`: 0 stays 0, the threshold becomes 1/2, 1 stays 1;
  ``soft=True``; a member's partial-volume boundary counts as a fraction), or of their binary calls
  (``soft=False``); 0 outside the working ball, where no object lies;
* ``std``: the members' standard deviation of that centred occupancy;
* ``p_wrong``: the probability that the reference reconstruction's binary call is wrong,
  ``1 - probability`` inside it, ``probability`` outside it (0 outside the working ball).

The keys ``std`` / ``p_wrong`` are those of :func:`dipnet.evaluation.uncertainty.voxel_maps`, so
:func:`~dipnet.evaluation.uncertainty.summarise` and :func:`~dipnet.evaluation.uncertainty.calibration_by_decile`
apply unchanged. :func:`brier_score` and :func:`reliability` measure how well a probability is
calibrated against a known truth, for this method and the linearised one alike
(:func:`occupancy_probability`).

Cost: ``n_samples`` solves of the job's solver (``iterations_scale`` shortens each).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage
import torch

from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.uncertainty import misfit_variance, summarise, support
from dipnet.operators import DipOperator
from dipnet.solvers.base import Solver
from dipnet.solvers.optimize import OptimisationSolver

START_AMPLITUDE = 0.3  # std of a random start's occupancy around the measured volume fraction
START_SMOOTH = 2.0  # Gaussian sigma (voxels) of a random start's field


@dataclass
class Ensemble:
    """Members' reconstructions of one measurement.

    Attributes:
        occupancies: each member's occupancy centred on its threshold, ``(S, *grid.shape)`` float32,
            ``clip(o - threshold + 1/2, 0, 1)``.
        binaries: each member's binary call, ``(S, *grid.shape)`` bool.
        noise_std: standard deviation of the profile perturbation, mm^3 per measured slab.
        seconds: wall time of all members.
    """

    occupancies: np.ndarray
    binaries: np.ndarray
    noise_std: float
    seconds: float


class RandomStart:
    """A random initial occupancy for an optimisation solver (its ``warm_start`` callable).

    A Gaussian field smoothed by ``smooth`` voxels, scaled to standard deviation ``amplitude``, around
    the level that fills the working ball with the measured volume, clipped to ``[0, 1]``.
    """

    def __init__(self, seed: int, amplitude: float = START_AMPLITUDE, smooth: float = START_SMOOTH) -> None:
        self.seed, self.amplitude, self.smooth = int(seed), float(amplitude), float(smooth)

    def __call__(self, measurement: DipMeasurement, operator: DipOperator) -> torch.Tensor:
        grid = operator.grid
        level = max(measurement.volume_estimate(), 0.0) / grid.extent ** grid.ndim \
            / float(grid.working_mask().double().mean())
        field = scipy.ndimage.gaussian_filter(np.random.default_rng(self.seed).standard_normal(grid.shape), self.smooth)
        field *= self.amplitude / max(float(field.std()), 1e-12)
        return torch.from_numpy(np.clip(min(level, 1.0) + field, 0.0, 1.0)).float()


def member(solver: Solver, index: int, seed: int, random_start: bool = True, iterations_scale: float = 1.0) -> Solver:
    """A copy of ``solver`` for ensemble member ``index``: quiet, without checkpoint or surface refit (the
    ensemble reads the members' occupancies, not their surfaces), its own seed (``seed + 1 + index``),
    a :class:`RandomStart` when it is an optimisation solver without a warm start (and not one whose seed already draws
    its start, ``seeded_start``), and ``iterations_scale`` of its iterations. A nested warm-start solver
    (``voxel_learned``'s plain voxel start, and any start of that start) is copied too, quiet and with the member's
    seed, as the configs tie it (``warm_start.seed: ${seed}``), and the innermost one gets the :class:`RandomStart`
    instead (the voxel solver's seed draws nothing): a shared seed and start would leave members differing by their
    perturbed data alone."""
    out = copy.copy(solver)
    member_seed = int(seed) + 1 + int(index)
    for name, value in (("progress", False), ("checkpoint", None), ("surface_refit", None), ("seed", member_seed)):
        if hasattr(out, name):
            setattr(out, name, value)
    _nested_members(out, member_seed, random_start)
    if isinstance(out, OptimisationSolver):
        out.iterations = max(1, round(out.iterations * iterations_scale))
        if random_start and out.warm_start is None and not getattr(out, "seeded_start", False):
            out.warm_start = RandomStart(member_seed)
    return out


def _nested_members(solver: Solver, member_seed: int, random_start: bool = True) -> None:
    """Replace the warm-start solver of ``solver`` (a member's copy), and its own, recursively, by copies that are
    quiet and seeded with ``member_seed`` (a start that is no solver, a tensor or a callable, is kept); with
    ``random_start`` the innermost, when it is an optimisation solver without a start (nor ``seeded_start``), starts
    from a :class:`RandomStart` of ``member_seed``."""
    nested = False
    while isinstance(getattr(solver, "warm_start", None), Solver):
        solver.warm_start, nested = copy.copy(solver.warm_start), True
        solver = solver.warm_start
        for name, value in (("progress", False), ("seed", member_seed)):
            if hasattr(solver, name):
                setattr(solver, name, value)
    if nested and random_start and isinstance(solver, OptimisationSolver) and solver.warm_start is None \
            and not getattr(solver, "seeded_start", False):
        solver.warm_start = RandomStart(member_seed)


def perturbed(measurement: DipMeasurement, std: float, rng: np.random.Generator) -> DipMeasurement:
    """``measurement`` with white Gaussian noise of ``std`` (mm^3) added to every slab volume."""
    noise = torch.from_numpy(rng.standard_normal(tuple(measurement.profiles.shape)) * std)
    return replace(measurement, profiles=measurement.profiles + noise)


def profile_noise_std(reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator) -> float:
    """The perturbation's std (mm^3) on the measurement's slabs: the linearised posterior's noise
    variance (:func:`~dipnet.evaluation.uncertainty.misfit_variance`, on the operator's slabs) rescaled
    to the measurement's slab thickness (a sum of independent errors: variance proportional to thickness)."""
    ratio = measurement.slab_thickness / operator.slab_thickness
    return math.sqrt(misfit_variance(reconstruction, measurement, operator) * ratio)


def check_ensemble_options(n_samples: int, iterations_scale: float) -> None:
    """Raise ``ValueError`` for what :func:`sample_ensemble` cannot use: fewer than 2 members ``n_samples`` (no
    spread), or an ``iterations_scale`` (the share of the solver's iterations each member runs) outside ``(0, 1]``."""
    if int(n_samples) < 2:
        raise ValueError(f"an ensemble needs n_samples >= 2, got {n_samples}")
    if not 0 < iterations_scale <= 1:
        raise ValueError(f"iterations_scale must be in (0, 1], got {iterations_scale}")


def sample_ensemble(solver: Solver, reconstruction: Reconstruction, measurement: DipMeasurement,
                    operator: DipOperator, *, n_samples: int = 4, seed: int = 0, perturb: bool = True,
                    random_start: bool = True, iterations_scale: float = 1.0) -> Ensemble:
    """Solve ``n_samples`` perturbed copies of ``measurement`` with members of ``solver`` (module docstring).

    Args:
        solver: the job's solver (copied, never changed).
        reconstruction: the job's reconstruction (sets the noise level from its misfit).
        measurement, operator: the job's data and dip operator.
        n_samples: members ``S`` (at least 2).
        seed: seeds the perturbations and the members (member ``s`` gets ``seed + 1 + s``).
        perturb: add the noise draw to the profiles (``False``: members differ by seed and start only).
        random_start: give optimisation solvers a :class:`RandomStart`.
        iterations_scale: fraction of the solver's iterations each member runs, in ``(0, 1]``.
    """
    check_ensemble_options(n_samples, iterations_scale)
    started = time.perf_counter()
    std = profile_noise_std(reconstruction, measurement, operator) if perturb else 0.0
    rng = np.random.default_rng(int(seed))
    occupancies, binaries = [], []
    for s in range(int(n_samples)):
        data = perturbed(measurement, std, rng) if perturb else measurement
        recon = member(solver, s, seed, random_start, iterations_scale).solve(data, operator)
        occupancies.append(centred_occupancy(recon.occupancy.detach().double().numpy(), recon.threshold))
        binaries.append(np.asarray(recon.binary, bool))
    return Ensemble(np.stack(occupancies), np.stack(binaries), std, time.perf_counter() - started)


def centred_occupancy(occupancy: np.ndarray, threshold: float) -> np.ndarray:
    """``occupancy`` (any shape) mapped piecewise linearly so that 0 stays 0, ``threshold`` becomes 1/2 and 1 stays 1,
    clipped to [0, 1] (float32): a member's probability of occupancy, whatever level it thresholds at. Shifting by
    ``1/2 - threshold`` instead gave an empty voxel of a member thresholded at 0.2 (``minnorm``'s Otsu level) a
    probability of 0.3."""
    t = min(max(float(threshold), 1e-6), 1.0 - 1e-6)
    o = np.asarray(occupancy, dtype=np.float64)
    mapped = np.where(o <= t, 0.5 * o / t, 0.5 + 0.5 * (o - t) / (1.0 - t))
    return np.clip(mapped, 0.0, 1.0).astype(np.float32)


def ensemble_maps(reference: Reconstruction, ensemble: Ensemble, soft: bool = True) -> dict[str, np.ndarray]:
    """``probability``, ``std`` and ``p_wrong`` (float32 volumes, ``grid.shape``) of the reference's
    binary calls under ``ensemble`` (module docstring)."""
    values = ensemble.occupancies if soft else ensemble.binaries.astype(np.float32)
    inside = np.asarray(reference.binary, bool)
    working = reference.grid.working_mask().numpy()
    probability = np.where(working, values.mean(axis=0), 0.0)
    p_wrong = np.where(working, np.where(inside, 1.0 - probability, probability), 0.0)
    return {"probability": probability.astype(np.float32), "std": ensemble.occupancies.std(axis=0, ddof=1),
            "p_wrong": p_wrong.astype(np.float32)}


def ensemble_uncertainty(reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator,
                         solver: Solver, soft: bool | None = None, **options
                         ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Maps (:func:`ensemble_maps`) and their summary (:func:`~dipnet.evaluation.uncertainty.summarise`,
    plus ``uncertainty_samples``, ``uncertainty_noise_std`` mm^3 and ``uncertainty_seconds``); ``options``
    go to :func:`sample_ensemble`. ``soft``: average the members' occupancies or their binary calls; ``None``:
    the occupancies for the optimisation solvers (in [0, 1] about their level), the calls for the others, whose
    linear field is no probability: ``minnorm``'s ripples of 0.1-0.2 far outside the chamber box (24^3, 120 dips,
    Otsu level 0.44) made its ``expected_error_fraction`` 0.47 where 0.04 of it was wrong."""
    if soft is None:
        soft = isinstance(solver, OptimisationSolver)
    ensemble = sample_ensemble(solver, reconstruction, measurement, operator, **options)
    maps = ensemble_maps(reconstruction, ensemble, soft)
    summary = summarise(maps, reconstruction.binary)
    summary.update(uncertainty_samples=len(ensemble.occupancies), uncertainty_noise_std=ensemble.noise_std,
                   uncertainty_seconds=ensemble.seconds)
    return maps, summary


def occupancy_probability(p_wrong: np.ndarray, binary: np.ndarray) -> np.ndarray:
    """The occupancy probability that ``p_wrong`` implies for the calls ``binary``: ``1 - p_wrong``
    inside, ``p_wrong`` outside (turns the linearised method's map into a probability)."""
    return np.where(np.asarray(binary, bool), 1.0 - np.asarray(p_wrong, float), np.asarray(p_wrong, float))


def _scored(binary: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The voxels a calibration score looks at: the support of ``binary`` and the true object."""
    return support(binary) | np.asarray(truth, bool)


def brier_score(probability: np.ndarray, binary: np.ndarray, truth: np.ndarray) -> float:
    """Mean squared error of the occupancy ``probability`` against ``truth`` (bool) over the support of
    the calls ``binary`` and the true object (0: certain and right; a hard 0/1 call scores its error rate);
    NaN when both are empty (no voxel to score)."""
    where = _scored(binary, truth)
    if not where.any():
        return float("nan")
    return float(np.mean((np.asarray(probability, float)[where] - np.asarray(truth, bool)[where]) ** 2))


def reliability(probability: np.ndarray, binary: np.ndarray, truth: np.ndarray, n_bins: int = 10
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Reliability of the occupancy ``probability`` over the same voxels as :func:`brier_score`.

    Voxels fall into ``n_bins`` equal-width probability bins; per bin the mean predicted probability,
    the observed occupied fraction (both ``nan`` when empty) and the voxel count, ``(n_bins,)`` each,
    and the expected calibration error ``sum_b (count_b / total) |predicted_b - observed_b|``.
    """
    where = _scored(binary, truth)
    p = np.clip(np.asarray(probability, float)[where], 0.0, 1.0)
    t = np.asarray(truth, bool)[where]
    index = np.minimum((p * n_bins).astype(int), n_bins - 1)
    count = np.bincount(index, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.bincount(index, p, minlength=n_bins) / count
        observed = np.bincount(index, t.astype(float), minlength=n_bins) / count
    filled = count > 0
    ece = float(np.sum(count[filled] * np.abs(predicted[filled] - observed[filled])) / max(int(count.sum()), 1))
    return predicted, observed, count, ece
