"""The optimisation loop shared by the voxel and implicit solvers.

Objective (every term dimensionless, so weights mean the same at any resolution and unit):

    L = sum_km w_km (A o - g)_km^2 / sum_km w_km g_km^2  +  sum_p lambda_p R_p(o)

``A`` is the dip operator, ``o`` the occupancy on its grid, ``g`` the measured slab volumes
(:func:`~dipnet.solvers.base.measured_profiles`), ``w = 1 / sigma^2`` when the measurement
gives its noise ``sigma`` (else 1), and ``R_p`` the priors of :mod:`dipnet.solvers.priors`.
The data term is the (weighted) squared relative residual: 1 for an empty volume, about
``10^(-SNR/10)`` at the noise floor.
With ``noise_model="correlated"`` (and ``sigma``) the slabs of a profile are weighed by the inverse
of their covariance instead (:class:`DataTerm`): a slab volume is the difference of two cumulative
readings, so neighbouring slabs' errors are anti-correlated.

:class:`OptimisationSolver` holds the options shared by both solvers; :func:`optimise` runs
Adam (with a cosine, step or constant learning-rate schedule) or L-BFGS, stops early when
the loss plateaus (:func:`plateaued`), shows the terms in a progress bar and returns their history.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import contextmanager
from typing import NamedTuple

import torch
from torch import nn
from tqdm.auto import tqdm

from dipnet.core.flags import checked_flag
from dipnet.core.grid import Grid
from dipnet.core.counts import is_real, whole_number
from dipnet.core.measurement import DipMeasurement, filled_slabs, robust_volume
from dipnet.operators import DipOperator
from dipnet.core.reconstruction import Reconstruction
from dipnet.shapes.isosurface import enclosed_volume, level_for_volume
from dipnet.solvers.base import (SIGMA_FLOOR, SMOOTHED_NOISE_MODEL, Solver, checked_threshold,
                                 measured_profiles, noise_sigma, readings_differenced)
from dipnet.solvers.checkpoint import solver_settings, tensor_digest
from dipnet.solvers.noise_covariance import correlated_precision
from dipnet.solvers.progress import stop_bar
from dipnet.solvers.priors import SymmetryPrior, build_priors, checked_priors
from dipnet.solvers.weights import KNOWN_NOISE, WeightRule, auto_names, noise_level, with_weight
from dipnet.solvers.learned import object_fill
from dipnet.solvers.surface_refit import SurfaceRefit

log = logging.getLogger(__name__)

OPTIMIZERS = ("adam", "lbfgs")
SCHEDULES = ("cosine", "step", "constant")
_HULL_ENTRIES = 1 << 25  # column x orientation bounds held at once by support_hull
_FLAT = 1e-12  # |theta_z| below this: a slab parallel to the hull's columns
VOLUME_LEVELS = (0.25, 0.75)  # the levels threshold='volume' searches
GAIN_LR = 0.01  # Adam step of the log-gain (fit_gain): a few steps per percent, no overshoot

Priors = list[tuple[str, float, nn.Module]]


class Problem(NamedTuple):
    """What a solver optimises on one grid."""

    data: "DataTerm"
    priors: Priors  # "auto" weights at the weight rule's start (see OptimisationSolver.choose_weights)
    volume_fraction: float  # measured object volume / grid cube volume
    support: torch.Tensor  # bool, grid.shape: voxels that may be occupied
    # the data term of the noise alone (weights.noise_level, or DataTerm.expected_noise) and its source
    noise: tuple[float, str]
    spec: Mapping[str, Mapping]  # the priors' options ("auto" weights unresolved) that ``priors`` was built from


NOISE_MODELS = ("independent", "correlated")


def checked_white_share(white_share: float) -> float:
    """The correlated noise model's white part (units of ``sigma^2 / 2``) as a float: a finite number > 0, else a
    ``ValueError`` (an infinite white part weighs every slab by 0: no data term, an empty result)."""
    if not is_real(white_share) \
            or not 0 < white_share < math.inf:
        raise ValueError(f"white_share must be a finite number > 0 (the white part, in sigma^2 / 2), got {white_share}")
    return float(white_share)


class DataTerm(nn.Module):
    """Weighted squared relative residual ``sum w (a A o - g)^2 / sum w g^2`` (see module docstring).

    ``noise_model="correlated"`` (with ``sigma`` given) weighs each profile's residual ``r_k`` by the
    inverse of the covariance a level sensor or balance gives its slabs: each slab volume is the
    difference of the cumulative submerged volume at its two edges, read with independent errors
    of variance ``sigma^2 / 2``, so neighbouring slabs' errors are anti-correlated (lag-1
    correlation -1/2; -0.51 to -0.54 measured on simulated 30 dB scans) and a profile's sum is
    known about ``sqrt(M)`` times better than independent slabs say. A white part of variance
    ``white_share x sigma^2 / 2`` is added (the model's own error; without it the low frequencies of
    a profile weigh about ``M^2`` times the high ones and Adam does not converge in the solvers'
    steps). Over each profile's filled span (its first to last filled slab; before it the baseline
    is exact, after it the readings repeat the total):
    ``sum_k r_k^T Sigma_k^-1 r_k / sum w g^2``; outside the span the slabs count as independent.
    :attr:`expected_noise` is the term's expected value for the differenced noise alone (what the
    weight rule and the rounds' discrepancy check compare with). It holds a ``(K, M, M)`` precision.

    ``a`` is 1, or with ``fit_gain`` a free gain ``a = exp(log_gain)`` optimised with the shape:
    one unknown factor on every measured volume, which is what a wrong tank cross-section does
    (the readers multiply each level rise by the cross-section they assume, so
    ``a = assumed / true cross-section``).

    Args:
        operator: the dip operator ``A``.
        target: measured slab volumes ``(K, M)`` on the operator's slabs, mm^3.
        sigma: optional noise standard deviation ``(K, M)``, mm^3.
        dtype: arithmetic dtype of the residual.
        fit_gain: make ``log_gain`` a parameter (:attr:`log_gain`).
        log_gain: its starting value.
        noise_model: ``"independent"`` slabs, or ``"correlated"`` (above; without ``sigma`` the slabs
            count as independent).
        white_share: the white part's variance in units of ``sigma^2 / 2`` (``"correlated"``).
        rel_tol: a slab is filled when its volume exceeds this share of its profile's largest.
        differenced: whether the slabs are the differences of cumulative readings as read; profiles smoothed in
            preprocessing are not (:func:`~dipnet.solvers.base.readings_differenced`), and ``"correlated"`` then
            counts them as independent.

    :attr:`noise_model` is the model the term uses: ``"correlated"`` (with a ``(K, M, M)`` :attr:`precision`),
    ``"independent"``, or :data:`~dipnet.solvers.base.SMOOTHED_NOISE_MODEL` when ``"correlated"`` was asked for
    smoothed profiles.
    """

    def __init__(self, operator: DipOperator, target: torch.Tensor, sigma: torch.Tensor | None = None,
                 dtype: torch.dtype = torch.float32, fit_gain: bool = False, log_gain: float = 0.0,
                 noise_model: str = "independent", white_share: float = 1.0, rel_tol: float = 0.005,
                 differenced: bool = True) -> None:
        super().__init__()
        if noise_model not in NOISE_MODELS:
            raise ValueError(f"unknown noise_model {noise_model!r}; choose one of {NOISE_MODELS}")
        white_share = checked_white_share(white_share)
        self.operator = operator
        self.log_gain = nn.Parameter(torch.tensor(float(log_gain), dtype=dtype)) if fit_gain else None
        if sigma is None or not bool((sigma > 0).any()):
            sigma, weight = None, torch.ones_like(target)
        else:
            sigma = sigma.to(target.dtype)
            sigma = sigma.clamp(min=SIGMA_FLOOR * float(sigma[sigma > 0].median()))
            weight = sigma.pow(-2)
        norm = float((weight * target.pow(2)).sum().clamp(min=1e-300))
        self.register_buffer("target", target.to(dtype))
        self.register_buffer("weight", (weight / norm).to(dtype))
        self.register_buffer("precision", None)  # (K, M, M) with noise_model="correlated" and sigma
        self.expected_noise: float | None = None
        self.noise_model = "independent"
        if noise_model == "correlated" and sigma is not None and not differenced:
            self.noise_model = SMOOTHED_NOISE_MODEL
        elif noise_model == "correlated" and sigma is not None:
            noise = correlated_precision(target, sigma, white_share, rel_tol)
            self.precision, self.expected_noise = (noise.precision / norm).to(dtype), noise.expected / norm
            self.noise_model = "correlated"

    @property
    def gain(self) -> float:
        """The fitted gain ``a`` (1 without ``fit_gain``)."""
        return 1.0 if self.log_gain is None else math.exp(float(self.log_gain.detach()))

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        predicted = self.operator(occupancy)
        if self.log_gain is not None:
            predicted = predicted * torch.exp(self.log_gain)
        residual = predicted - self.target
        if self.precision is not None:
            return torch.einsum("km,kmn,kn->", residual, self.precision, residual)
        return (self.weight * residual.pow(2)).sum()


def support_hull(target: torch.Tensor, grid: Grid, directions: torch.Tensor, edges: torch.Tensor,
                 rel_tol: float = 0.005, margin: float = 1.5, chunk: int | None = None) -> torch.Tensor:
    """Voxels that can hold material: the working ball cut by every orientation's slab support.

    For orientation ``k`` the object lies between the lower edge of its first and the upper
    edge of its last non-empty slab (a slab is empty when its volume is at most ``rel_tol``
    times the profile's largest); voxel centres beyond that range by more than ``margin``
    voxels cannot be occupied. The intersection over all orientations is a polytope around
    the object's convex hull, found from the data alone. Noise only makes empty slabs look
    full, which widens the hull (safe); a threshold from the noise sigma would instead cut
    the object's thin tips, whose slabs hold less than a few sigma, so none is used.

    The polytope is convex, so each column of voxels along the last coordinate (z in 3D, y
    in 2D) meets it in one interval: every slab ``lo_k <= x . theta_k <= hi_k`` bounds that
    coordinate from below and above (or keeps all / none of the column when ``theta_k`` has
    no component along it), and the column keeps the voxels between the largest lower and
    the smallest upper bound. Cost ``N^(d-1) K`` instead of ``N^d K`` (240^3 with 5,760
    directions: 3.3e8 bound evaluations instead of 8e10, 5 s of one core instead of more than
    7 min); the mask is the same as testing every voxel centre against every slab, up to
    rounding at exact ties. Slabs with ``|theta_z| <= 1e-12`` count as parallel to the columns.

    Args:
        target: measured slab volumes ``(K, M)``, mm^3.
        grid: the grid of the mask (any resolution).
        directions: unit directions ``(K, d)``.
        edges: slab edges ``(M + 1,)`` in mm.
        rel_tol: emptiness threshold relative to each profile's maximum.
        margin: slack in voxels.
        chunk: orientations bounded at once (default: as many as keep the ``(columns,
            chunk)`` bounds near ``2^25`` entries, 256 MB in float64: 582 at 240^3).

    Returns:
        Boolean mask ``grid.shape`` (a subset of the working ball).

    Raises:
        EmptySupportError: no voxel is left (the profiles of different dips do not overlap).
    """
    lo, hi = slab_support(target, edges, rel_tol, margin * grid.voxel_size)
    dirs = directions.to(target.dtype)
    axis = grid.axis(target.dtype)  # centre coordinates along a column, mm
    across_axes = torch.meshgrid(*([axis] * (grid.ndim - 1)), indexing="ij")  # array order ([y,] x)
    columns = torch.stack(across_axes[::-1], dim=-1).reshape(-1, grid.ndim - 1)  # (N^(d-1), d-1): (x[, y]), mm
    along = dirs[:, -1]
    flat = along.abs() <= _FLAT
    chunk = chunk or max(1, _HULL_ENTRIES // columns.shape[0])
    # tilted slabs: lo <= x.theta_xy + z theta_z <= hi  <=>  z between two planes over the columns
    tilted, t_along = dirs[~flat], along[~flat]
    start = torch.where(t_along > 0, lo[~flat], hi[~flat]) / t_along  # z bound at the column x = 0
    stop = torch.where(t_along > 0, hi[~flat], lo[~flat]) / t_along
    slope = -tilted[:, :-1] / t_along[:, None]  # dz / dx of both bounds, (K', d-1)
    floor = _envelope(columns, slope, start, chunk, upper=True)
    ceiling = _envelope(columns, slope, stop, chunk, upper=False)
    keep = torch.ones(columns.shape[0], dtype=torch.bool)  # flat slabs keep a column whole or not at all
    for k0 in range(0, int(flat.sum()), chunk):
        across = columns @ dirs[flat][k0:k0 + chunk, :-1].T
        keep &= ((across >= lo[flat][k0:k0 + chunk]) & (across <= hi[flat][k0:k0 + chunk])).all(dim=1)
    first = torch.searchsorted(axis, floor.contiguous(), right=False)  # first centre >= floor
    last = torch.where(keep, torch.searchsorted(axis, ceiling.contiguous(), right=True) - 1, -1)
    index = torch.arange(grid.n).reshape(-1, *([1] * (grid.ndim - 1)))
    shape = (1, *grid.shape[1:])
    hull = (index >= first.reshape(shape)) & (index <= last.reshape(shape)) & grid.working_mask()
    if not hull.any():
        raise EmptySupportError(
            f"the dips leave no voxel of the {grid.n}^{grid.ndim} grid that can hold the object: their profiles "
            "do not overlap inside the working ball (start heights or directions are wrong: calibrate the rig "
            "geometry, e.g. calibration=self, or check extent_mm)")
    return hull


class EmptySupportError(ValueError):
    """The data's support hull holds no voxel: the profiles are inconsistent with one object on the grid."""


class DivergedError(FloatingPointError, ValueError):
    """The loss of an optimisation became NaN or infinite (a learning rate too large for the problem);
    a ``ValueError`` so that the command line reports it in one line."""


def _envelope(columns: torch.Tensor, slope: torch.Tensor, offset: torch.Tensor, chunk: int, upper: bool
              ) -> torch.Tensor:
    """Upper (``max_k``) or lower (``min_k``) envelope of the planes ``offset_k + columns . slope_k``
    at each column, ``(P,)``; ``-inf`` / ``+inf`` when there is no plane. ``chunk`` planes at once."""
    out = torch.full((columns.shape[0],), -math.inf if upper else math.inf, dtype=columns.dtype)
    for k0 in range(0, offset.shape[0], chunk):
        planes = torch.addmm(offset[k0:k0 + chunk], columns, slope[k0:k0 + chunk].T)  # (P, chunk)
        out = torch.maximum(out, planes.amax(dim=1)) if upper else torch.minimum(out, planes.amin(dim=1))
    return out


def slab_support(target: torch.Tensor, edges: torch.Tensor, rel_tol: float, slack: float
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per orientation, the heights ``(lo, hi)`` (each ``(K,)``, mm) between which the object
    lies: the lower edge of the first and the upper edge of the last slab holding more than
    ``rel_tol`` of the profile's largest volume, widened by ``slack`` mm (all slabs when none does)."""
    full = filled_slabs(target, rel_tol)  # (K, M) non-empty slabs
    edges = edges.to(target.dtype)
    m = full.shape[1]
    first = torch.argmax(full.to(torch.int8), dim=1)
    last = m - 1 - torch.argmax(full.flip(1).to(torch.int8), dim=1)
    lo = torch.where(full.any(1), edges[first] - slack, edges[0] - slack)
    hi = torch.where(full.any(1), edges[last + 1] + slack, edges[-1] + slack)
    return lo, hi


def target_and_sigma(measurement: DipMeasurement, operator: DipOperator
                     ) -> tuple[torch.Tensor, torch.Tensor | None, str]:
    """Measured slab volumes on the operator's slabs ``(K, M)``, their noise sigma (``None`` when unknown) and
    its source (``"sigma"``, ``"readings"`` or ``"estimated"``: :func:`~dipnet.solvers.base.noise_sigma`)."""
    return measured_profiles(measurement, operator), *noise_sigma(measurement, operator)


def volume_fraction(measurement: DipMeasurement, operator: DipOperator) -> float:
    """Measured object volume (median profile sum) / volume of the grid cube."""
    return max(measurement.volume_estimate(), 0.0) / operator.grid.extent ** operator.grid.ndim


def _refuse_other_operators(priors: Priors, operator: DipOperator) -> None:
    """Priors made for one grid / operator (the learned prior) refuse others (their ``check_operator``)."""
    for _, _, module in priors:
        if hasattr(module, "check_operator"):
            module.check_operator(operator)


def plain(value):
    """``value`` with every mapping turned into a dict and every non-string sequence into a
    list, recursively (Hydra passes ``DictConfig`` / ``ListConfig``)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain(v) for v in value]
    return value


def optimise(parameters: Iterable, occupancy: Callable[[], torch.Tensor], data: DataTerm, priors: Priors, *,
             iterations: int, lr: float, optimizer: str = "adam", schedule: str = "cosine",
             tol: float = 1e-5, window: int = 25, progress: bool = True, desc: str = "optimise",
             before_step: Callable[[float], None] | None = None, checkpoint=None,
             options: Mapping | None = None) -> dict[str, list[float]]:
    """Minimise ``data(o) + sum weight * prior(o)`` over ``parameters``, with ``o = occupancy()``.

    Args:
        parameters: tensors or param-group dicts (a group may set its own ``lr``).
        occupancy: builds the occupancy volume on ``data.operator.grid`` from the parameters.
        data, priors: the data term and ``[(name, weight, module)]``.
        iterations: maximum number of steps (L-BFGS: outer steps with one line search each).
        lr: learning rate (Adam) / initial step (L-BFGS, typically 1).
        optimizer: ``"adam"`` or ``"lbfgs"``.
        schedule: Adam's learning-rate schedule: ``"cosine"`` (to 1% of ``lr``), ``"step"``
            (x0.3 at 50% and 75% of ``iterations``) or ``"constant"``.
        tol: stop when the best loss of the last ``window`` steps is less than ``tol`` relative
            below the best before them (:func:`plateaued`; ``tol=0``: never stop early).
        progress: show a progress bar with the current terms.
        desc: progress-bar label.
        before_step: called with the progress fraction ``i / iterations`` before each step
            (annealing hooks).
        checkpoint: a :class:`~dipnet.solvers.checkpoint.Checkpoint`: resume this stage (``desc``) from
            it and save to it as the steps go.
        options: the settings that shaped this stage beyond the arguments here (the solver's,
            :func:`~dipnet.solvers.checkpoint.solver_settings`); a checkpoint made with others is not resumed.

    Returns:
        History ``{"loss": total, "data": ..., <prior name>: unweighted value, ...}`` per step.

    Raises:
        DivergedError: the loss became NaN or infinite (naming ``desc``, the step and ``lr``).
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {OPTIMIZERS}")
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown schedule {schedule!r}; choose one of {SCHEDULES}")
    iterations = int(iterations)
    params = list(parameters)
    history: dict[str, list[float]] = {"loss": [], "data": [], **{name: [] for name, _, _ in priors}}
    last: dict[str, torch.Tensor] = {}

    def objective() -> torch.Tensor:
        opt.zero_grad(set_to_none=True)
        occ = occupancy()
        terms = {"data": data(occ), **{name: module(occ) for name, _, module in priors}}
        total = terms["data"] + sum(weight * terms[name] for name, weight, _ in priors)
        total.backward()
        last.update(terms, loss=total)
        return total

    flat = [p for g in params for p in (g["params"] if isinstance(g, dict) else [g])]
    if optimizer == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(params, lr=lr)
        sched = _scheduler(opt, schedule, iterations)
    else:
        opt = torch.optim.LBFGS(flat, lr=lr, max_iter=1, max_eval=25, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=0.0, tolerance_change=0.0)
        sched = None
    op = data.operator
    fingerprint = None if checkpoint is None else {  # hashes the data: only for a checkpoint to check
        "iterations": iterations, "optimizer": optimizer, "shapes": [list(p.shape) for p in flat],
        "target": tensor_digest(data.target, data.weight, data.precision), "terms": list(history),
        "operator": [type(op).__name__, *op.grid.shape, float(op.grid.extent), int(op.n_slabs),
                     tensor_digest(op.directions)], "options": plain(options or {}),
        "weights": [module.digest for _, _, module in priors if hasattr(module, "digest")]}
    first, ended = 0, False
    # priors whose next calls depend on more than the occupancy (a red mode learned prior's lag): checkpointed too
    lagged = {name: module for name, _, module in priors
              if hasattr(module, "lag_state") and module.lag_state() is not None}
    if checkpoint is not None:
        with torch.no_grad():  # an anchored prior's anchor is of the stage's start, not of the restored state
            start = occupancy()
            for _, _, module in priors:
                if hasattr(module, "anchor_at"):
                    module.anchor_at(start)
        first, saved, ended = checkpoint.restore(desc, fingerprint, flat, opt, sched, lagged)
        history = saved or history
        if first and before_step is not None:
            before_step((first - 1) / max(iterations, 1))  # the hooks' state after the last saved step
    with tqdm(total=iterations, initial=first, desc=desc, disable=not progress, leave=False) as bar:
        for i in range(iterations if ended else first, iterations):
            if before_step is not None:
                before_step(i / max(iterations, 1))
            if optimizer == "adam":
                objective()
                opt.step()
            else:
                opt.step(objective)
            if sched is not None:
                sched.step()
            for key in history:
                history[key].append(float(last[key].detach()))
            if i % 10 == 0 or i == iterations - 1:
                bar.set_postfix({k: f"{v[-1]:.3g}" for k, v in history.items()}, refresh=False)
            bar.update()
            if not math.isfinite(history["loss"][-1]):
                raise DivergedError(f"{desc}: the loss became {history['loss'][-1]} at step {i + 1} of {iterations} "
                                    f"(learning rate {lr:g}): the optimisation diverged; try a lower solver.lr")
            done = plateaued(history["loss"], tol, window) or i == iterations - 1
            if checkpoint is not None:
                checkpoint.save(desc, fingerprint, i + 1, flat, opt, sched, history, done, lagged)
            if done:
                if i < iterations - 1:
                    stop_bar(bar, f"plateau at step {i + 1}")
                    log.info("%s: loss plateaued at step %d of %d (best of the last %d steps < %.2g below "
                             "the best before)", desc, i + 1, iterations, window, tol)
                break
    return history


def _scheduler(opt: torch.optim.Optimizer, schedule: str, iterations: int):
    if schedule == "cosine":
        return torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: 0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(i / iterations, 1.0))))
    if schedule == "step":
        return torch.optim.lr_scheduler.MultiStepLR(opt, [iterations // 2, (3 * iterations) // 4], gamma=0.3)
    return None


def plateaued(loss: Sequence[float], tol: float, window: int) -> bool:
    """True when the best loss of the last ``window`` steps is less than ``tol`` (relative)
    below the best loss before them: the run has stopped improving.

    Uses minima, not means, so the step-to-step jitter of Adam neither hides a plateau nor
    fakes progress; ``tol <= 0`` never stops.
    """
    if tol <= 0 or len(loss) < 2 * window:
        return False
    best_before = min(loss[:-window])
    best_recent = min(loss[-window:])
    return best_before - best_recent <= tol * max(abs(best_before), 1e-30)


def merge_histories(*histories: Mapping[str, list[float]]) -> dict[str, list[float]]:
    """Concatenate loss histories of consecutive stages (coarse then fine)."""
    out: dict[str, list[float]] = {}
    for hist in histories:
        for key, values in hist.items():
            out.setdefault(key, []).extend(values)
    return out


@contextmanager
def seeded(seed: int):
    """Run a block with torch's global RNG seeded, restoring its state afterwards."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        yield


class OptimisationSolver(Solver):
    """Options and plumbing shared by the optimisation solvers.

    Args:
        iterations: maximum optimisation steps.
        lr: learning rate (Adam) / initial step (L-BFGS).
        optimizer: ``"adam"`` or ``"lbfgs"``.
        schedule: ``"cosine"``, ``"step"`` or ``"constant"`` (Adam).
        tol, window: stop when the loss improved by less than ``tol`` (relative) over the last
            ``window`` steps (see :func:`plateaued`).
        priors: ``{name: {"weight": w, **options}}`` (see :func:`~dipnet.solvers.priors.build_priors`);
            ``w = "auto"`` chooses the weight from the data by ``weight_rule`` (:mod:`dipnet.solvers.weights`).
        weight_rule: options of :class:`~dipnet.solvers.weights.WeightRule` (the discrepancy principle).
        warm_start: initial occupancy: ``None`` (uniform, at the measured volume), a tensor
            ``grid.shape``, a solver (its ``solve(measurement, operator)`` result, e.g. a
            ``MinNormSolver``), or a callable ``(measurement, operator) -> tensor | Reconstruction``.
            A reconstruction's values are shifted so its threshold maps to 0.5, then clipped to [0, 1]; one on
            another grid than the operator's raises a ``ValueError``.
        hull_tol: voxels outside the data's :func:`support_hull` (with this ``rel_tol``) are
            fixed empty; ``None``: only the working ball.
        hull_margin: the hull's slack in voxels; raise it when the profiles' start heights
            are uncertain by more than about a voxel (real rigs before calibration).
        seed: seed of every random choice (initial weights, features).
        threshold: occupancy level of the final binary shape, in ``(0, 1)``, or ``"volume"``: the level (in
            :data:`VOLUME_LEVELS`) whose iso-surface encloses the measured volume (the robust mean
            of the profiles' totals, over the fitted gain), recorded in ``info["threshold_rule"]``.
            A soft occupancy's 0.5 surface lies inside a convex part's true surface, so it can
            enclose a few percent too little; the measured volume is known far better than that.
        progress: show progress bars.
        checkpoint: a :class:`~dipnet.solvers.checkpoint.Checkpoint` to save every stage to and resume from.
        fit_gain: also fit one gain on every predicted volume (:class:`DataTerm`); the result's
            ``info["gain"]`` holds it. Self-calibration uses it to estimate the tank's
            cross-section jointly with the shape (:func:`dipnet.calibration.self_calibration.self_calibrate`).
        noise_model, white_share: how the data term weighs the slabs' errors when the measurement
            gives their sigma (:class:`DataTerm`): ``"independent"``, or ``"correlated"`` (the
            differences of independent cumulative readings, plus a white part).
        surface_refit: ``None`` (off), or the options of a
            :class:`~dipnet.solvers.surface_refit.SurfaceRefit` (a mapping, ``{}`` for its defaults): a 3D result's
            surface is refitted to the dips as a mesh (:attr:`Reconstruction.mesh`) when held-out dips say the
            refit generalises, recorded in ``info["surface_refit"]``.
    """

    name = "optimisation"

    def __init__(self, iterations: int = 500, lr: float = 0.05, optimizer: str = "adam", schedule: str = "cosine",
                 tol: float = 1e-3, window: int = 25, priors: Mapping[str, Mapping] | None = None,
                 warm_start=None, hull_tol: float | None = 0.005, seed: int = 0, threshold: float | str = 0.5,
                 progress: bool = True, hull_margin: float = 1.5, checkpoint=None, fit_gain: bool = False,
                 weight_rule: Mapping | None = None, noise_model: str = "independent",
                 white_share: float = 1.0, surface_refit: Mapping | SurfaceRefit | None = None) -> None:
        if noise_model not in NOISE_MODELS:
            raise ValueError(f"unknown noise_model {noise_model!r}; choose one of {NOISE_MODELS}")
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {OPTIMIZERS}")
        if schedule not in SCHEDULES:
            raise ValueError(f"unknown schedule {schedule!r}; choose one of {SCHEDULES}")
        for name, value in (("iterations", iterations), ("window", window)):
            whole_number(name, value, low=1)
        if not is_real(lr) or not 0 < lr < math.inf:
            raise ValueError(f"lr must be a positive, finite learning rate, got {lr!r}")
        priors = plain(checked_priors("priors", priors) or {})
        self.weight_rule = WeightRule.from_options(plain(weight_rule or {}))
        build_priors(with_weight(priors, self.weight_rule.start), volume_fraction=1.0)  # validate now
        self.iterations, self.lr, self.optimizer, self.schedule = int(iterations), float(lr), optimizer, schedule
        if not is_real(tol) or not -math.inf < tol < math.inf:
            raise ValueError(f"tol must be a finite number (the plateau's relative improvement; <= 0: no early stop), "
                             f"got {tol!r}")  # NaN never stopped early, inf stopped after the first window
        self.tol, self.window = float(tol), int(window)
        self.priors = priors
        self._weights_choices: list[dict] = []  # the learned prior's choices among candidate weights, per solve
        self._plan_warnings: list[str] = []  # and its warnings of dips or an object unlike its training ones
        if hull_tol is not None and not 0 <= hull_tol < 1:
            raise ValueError(f"hull_tol must be in [0, 1) or None, got {hull_tol}")
        self.threshold = checked_threshold(threshold, "volume")
        if not (warm_start is None or isinstance(warm_start, (torch.Tensor, Reconstruction)) or callable(warm_start)
                or hasattr(warm_start, "solve")):  # 5 was refused after the simulation, naming the tensor's shape
            raise ValueError(f"warm_start must be null, a solver (a config with _target_, e.g. "
                             f"{{_target_: dipnet.solvers.MinNormSolver}}), an occupancy tensor, a reconstruction "
                             f"or a callable, got {warm_start!r}")
        self.warm_start, self.seed = warm_start, whole_number("seed", seed, low=0)  # 1.5 was cut to 1 unsaid
        self.progress = checked_flag("progress", progress)
        self.hull_tol = None if hull_tol is None else float(hull_tol)
        if not hull_margin >= 0:
            raise ValueError(f"hull_margin must be >= 0 voxels, got {hull_margin}")
        self.hull_margin = float(hull_margin)
        self.checkpoint = checkpoint
        self.fit_gain = checked_flag("fit_gain", fit_gain)
        self.noise_model, self.white_share = noise_model, checked_white_share(white_share)
        self.surface_refit = surface_refit if surface_refit is None or isinstance(surface_refit, SurfaceRefit) \
            else SurfaceRefit.from_options(plain(surface_refit) if isinstance(surface_refit, Mapping)
                                           else surface_refit)

    def _loop(self, parameters, occupancy, data: DataTerm, priors: Priors, iterations: int, desc: str,
              before_step=None, lr_scale: float = 1.0) -> dict[str, list[float]]:
        if data.log_gain is not None:
            parameters = [{"params": list(parameters)}, {"params": [data.log_gain], "lr": GAIN_LR}]
        return optimise(parameters, occupancy, data, priors, iterations=iterations, lr=self.lr * lr_scale,
                        optimizer=self.optimizer, schedule=self.schedule, tol=self.tol, window=self.window,
                        progress=self.progress, desc=desc, before_step=before_step, checkpoint=self.checkpoint,
                        options=None if self.checkpoint is None else solver_settings(self))

    def choose_weights(self, problem: Problem, parameters: list, occupancy: Callable[[], torch.Tensor], steps: int,
                       desc: str) -> tuple[dict[str, list[float]], Priors, dict]:
        """After a run with ``problem.priors`` (``"auto"`` weights at the rule's ``start``), choose
        those weights by :attr:`weight_rule` and refit ``parameters`` with them.

        The first run's data term ``D`` gives the weight
        (:meth:`~dipnet.solvers.weights.WeightRule.next_weight`); when it differs from the start,
        ``refit`` x ``steps`` more steps (learning rate x ``refit_lr``) continue from the first run's
        state. Returns the refit's history (``{}`` without one), the priors of the result and the
        record of the choice (``{"rule": "fixed"}`` when no weight is ``"auto"``).
        """
        if not auto_names(problem.spec):
            return {}, problem.priors, {"rule": "fixed"}
        rule, data = self.weight_rule, problem.data

        def residual() -> float:
            with torch.no_grad():
                return float(data(occupancy()))

        first = residual()
        weight = rule.next_weight(rule.start, first, problem.noise[0], may_raise=problem.noise[1] in KNOWN_NOISE)
        priors, history = problem.priors, {}
        if weight != rule.start:
            priors = build_priors(with_weight(problem.spec, weight), problem.volume_fraction)
            history = self._loop(parameters, occupancy, data, priors, max(1, round(rule.refit * steps)),
                                 f"{desc} refit", lr_scale=rule.refit_lr)
        record = {**rule.record(weight, first, residual(), problem.noise), "refit_steps": len(history.get("loss", []))}
        log.info("%s: prior weight %.3g (%s; relative residual %.3g, then %.3g; noise %.3g from %s)", desc, weight,
                 record["reason"], record["first_residual"], record["residual_reached"], record["noise_residual"],
                 record["noise_source"])
        return history, priors, record

    def _problem(self, measurement: DipMeasurement, operator: DipOperator, fit_gain: bool | None = None,
                 priors: Mapping[str, Mapping] | None = None) -> Problem:
        """Data term (fitting a gain with ``fit_gain``, default :attr:`fit_gain`), priors (those of
        ``priors``, default :attr:`priors`), measured volume fraction and support mask for ``operator``."""
        spec = self.priors if priors is None else priors
        target, sigma, source = target_and_sigma(measurement, operator)
        fraction = volume_fraction(measurement, operator)
        support = self.support(target, operator, operator.grid)
        rel_tol = self.hull_tol if self.hull_tol is not None else 0.005
        data = DataTerm(operator, target, sigma, fit_gain=self.fit_gain if fit_gain is None else fit_gain,
                        noise_model=self.noise_model, white_share=self.white_share, rel_tol=rel_tol,
                        differenced=readings_differenced(measurement))
        noise = (noise_level(target, sigma, data.weight, rel_tol)[0], source)
        if data.expected_noise is not None:  # the correlated model's own expectation of the noise's term
            noise = (data.expected_noise, source)
        built = build_priors(with_weight(spec, self.weight_rule.start), fraction)
        _refuse_other_operators(built, operator)
        return Problem(data, built, fraction, support, noise, spec)

    def prior_specs(self) -> list[Mapping[str, Mapping]]:
        """Every priors spec a solve uses: :attr:`priors` (the voxel solver adds its later rounds')."""
        return [self.priors]

    def check_grid(self, grid: Grid, n_slabs: int) -> None:
        """Refuse ``grid`` with ``n_slabs`` slabs per profile when a prior of any of :meth:`prior_specs`, or of a
        warm-start solver's, was made for another (the learned prior's weights): what :meth:`check_priors` refuses
        of an operator on that grid, checked by a job before it simulates or reads any dip.

        Raises:
            PriorMismatchError: see :meth:`~dipnet.solvers.learned.LearnedPrior.check_grid`.
        """
        for spec in self.prior_specs():
            for _, _, module in build_priors(with_weight(spec, self.weight_rule.start), 1.0):
                if hasattr(module, "check_grid"):
                    module.check_grid(grid.ndim, grid.n, n_slabs)
        if hasattr(self.warm_start, "check_grid"):
            self.warm_start.check_grid(grid, n_slabs)

    def check_priors(self, operator: DipOperator, measurement: DipMeasurement | None = None) -> None:
        """Refuse ``operator`` when a prior of any of :meth:`prior_specs` was made for another grid or operator
        (the learned prior's weights), before a warm start or a first round spends minutes on it; warn once of
        each plan warning of the first spec's priors (:meth:`~dipnet.solvers.learned.LearnedPrior.plan_warning`: dips
        unlike those the weights were trained on; later rounds' weights refine a result anchored by the first's: the
        hemisphere's second stage after the 0-35 deg rig's first did better than ``solver=voxel`` on 14 of 16 meshes
        under that rig's plan); keep the learned prior's choices among candidate weights
        (:meth:`~dipnet.solvers.learned.LearnedPrior.select_for`) for ``info["learned_weights"]``. With the
        ``measurement`` (on ``operator``'s slabs), warn as well of an object much smaller in the grid than the weights'
        training objects (:meth:`~dipnet.solvers.learned.LearnedPrior.size_warning`). None of these when a warm start
        with a learned prior of its own warns of them (:meth:`_start_warns_of_plan`).

        Raises:
            PriorMismatchError: see :meth:`~dipnet.solvers.learned.LearnedPrior.check_operator`.
        """
        said, self._weights_choices, self._plan_warnings = set(), [], []
        start_warns = self._start_warns_of_plan()
        for index, spec in enumerate(self.prior_specs()):
            built = build_priors(with_weight(spec, self.weight_rule.start), 1.0)
            _refuse_other_operators(built, operator)
            for _, _, module in built:
                choice = getattr(module, "choice", None)
                if choice is not None and choice["reason"] is not None and choice not in self._weights_choices:
                    self._weights_choices.append(dict(choice))
                    log.info("learned prior: weights %s: %s", choice["weights"], choice["reason"])
                first = index == 0 and hasattr(module, "plan_warning") and not start_warns
                messages = [module.plan_warning(operator.directions)] if first else []
                if first and measurement is not None and hasattr(module, "size_warning"):
                    grid = operator.grid
                    messages.append(module.size_warning(object_fill(measurement.profiles, measurement.slab_thickness,
                                                                    grid.radius)))
                for message in messages:
                    if message is not None and message not in said:
                        said.add(message)
                        self._plan_warnings.append(message)
                        warnings.warn(message, stacklevel=2)

    def _start_warns_of_plan(self) -> bool:
        """Whether the warm start is a solver whose first priors spec holds a learned prior: its own solve warns of
        the dips and the object against those first-stage weights, and this solve's learned prior refines that
        start's result (``solver=implicit_learned``'s ``denoiser64_stage2`` after ``solver=voxel_learned``), so it
        does not warn of them again against its later-stage weights (the plan warning looks at the first stage)."""
        start = self.warm_start
        if not hasattr(start, "prior_specs") or not hasattr(start, "weight_rule"):
            return False
        spec = start.prior_specs()[0]
        return any(hasattr(module, "plan_warning")
                   for _, _, module in build_priors(with_weight(spec, start.weight_rule.start), 1.0))

    def support(self, target: torch.Tensor, operator: DipOperator, grid: Grid) -> torch.Tensor:
        """Boolean mask ``grid.shape`` of the voxels the solver may fill (see ``hull_tol``),
        from the measured slab volumes ``target`` on ``operator``'s slabs."""
        if self.hull_tol is None:
            return grid.working_mask()
        return support_hull(target, grid, operator.directions, operator.slab_edges(), self.hull_tol, self.hull_margin)

    def _initial_occupancy(self, measurement: DipMeasurement, operator: DipOperator) -> torch.Tensor | None:
        """The warm-start occupancy on ``operator.grid`` (float32, in [0, 1]) or ``None``."""
        self.check_priors(operator, measurement)
        start = self.warm_start
        if start is None:
            return None
        if isinstance(start, torch.Tensor):
            pass
        elif hasattr(start, "solve"):
            start = start.solve(measurement, operator)
        elif callable(start):
            start = start(measurement, operator)
        if isinstance(start, Reconstruction):
            chosen = start.info.get("learned_weights") or []  # the start's choice of weights is this result's too
            self._weights_choices += [choice for choice in chosen if choice not in self._weights_choices]
            said = start.info.get("learned_prior_warnings") or []  # and its warnings, which this solve leaves to it
            self._plan_warnings += [message for message in said if message not in self._plan_warnings]
            if not start.grid.matches(operator.grid):  # the same shape on other voxels would start elsewhere
                raise ValueError(f"warm start is a reconstruction on {start.grid}, the operator's grid is "
                                 f"{operator.grid}: their voxels are not the same places; solve the start on the "
                                 "operator's grid")
            start = start.occupancy.detach().float() - start.threshold + 0.5
        start = torch.as_tensor(start, dtype=torch.float32)
        if tuple(start.shape) != operator.grid.shape:
            raise ValueError(f"warm start has shape {tuple(start.shape)}, the grid {operator.grid.shape}")
        return start.clamp(0, 1)

    def _result(self, occupancy: torch.Tensor, operator: DipOperator, history: dict, started: float,
                data: DataTerm | None = None, priors: Priors | None = None, weights: dict | None = None,
                **info) -> Reconstruction:
        """The reconstruction with ``info`` (and ``info["gain"]`` when ``data`` fitted one); with
        ``priors`` (those of the result), ``info["prior_weights"]`` (``{name: weight}``) and ``info["symmetries"]``
        (the symmetries declared, as :meth:`~dipnet.solvers.priors.SymmetryPrior.spec` gives them: those of
        symmetry priors with a weight, after any in ``info``), and ``info["weight_rule"]``, the record of
        :meth:`choose_weights`; ``info["learned_weights"]``: the learned prior's choices among candidate weights
        (:meth:`check_priors`, and those of a warm start's solve); ``info["learned_prior_warnings"]``: its plan and
        size warnings (:meth:`check_priors`, and a warm start's); with ``data``, ``info["noise_model"]``: the model
        its slabs' errors were weighed by (:attr:`DataTerm.noise_model`)."""
        steps = len(history.get("loss", []))
        if data is not None and data.log_gain is not None:
            info["gain"] = data.gain
        if data is not None:
            info["noise_model"] = data.noise_model
        if priors is not None:
            info["prior_weights"] = {name: weight for name, weight, _ in priors}
            info["symmetries"] = info.get("symmetries", []) + [
                module.spec() for _, weight, module in priors if isinstance(module, SymmetryPrior) and weight > 0]
        if weights is not None:
            info["weight_rule"] = weights
        if self._weights_choices:
            info["learned_weights"] = [dict(choice) for choice in self._weights_choices]
        if self._plan_warnings:
            info["learned_prior_warnings"] = list(self._plan_warnings)
        info = {"solver": self.name, "seconds": time.perf_counter() - started, "iterations": steps,
                "final": {k: v[-1] for k, v in history.items() if v}, "optimizer": self.optimizer,
                "seed": self.seed, **info}
        occupancy = occupancy.detach().float() * operator.mask
        level = self.level(occupancy, operator.grid, data)
        if self.threshold == "volume":
            info["threshold_rule"] = {"rule": "volume", "level": level, "measured_volume_mm3": self._volume(data),
                                      "enclosed_volume_mm3": enclosed_volume(occupancy, operator.grid, level)}
        return Reconstruction(occupancy=occupancy, grid=operator.grid, threshold=level, history=history, info=info)

    def _refit_surface(self, recon: Reconstruction, measurement: DipMeasurement,
                       operator: DipOperator) -> Reconstruction:
        """``recon`` with its surface refitted to ``measurement`` (on ``operator``'s slabs) by :attr:`surface_refit`
        (itself when that is off; with ``fit_gain`` the refit is skipped and says why: the dips' scale is the
        fitted gain's, not the measured one)."""
        if self.surface_refit is None:
            return recon
        if self.fit_gain:
            recon.info["surface_refit"] = {"applied": False, "reason": "fit_gain: the dips' scale is being fitted"}
            return recon
        target, sigma, _ = target_and_sigma(measurement, operator)
        return self.surface_refit.refit(recon, target, sigma, operator.directions, operator.slab_edges(),
                                        progress=self.progress,
                                        differenced=readings_differenced(measurement))

    def level(self, occupancy: torch.Tensor, grid: Grid, data: DataTerm | None) -> float:
        """The level of the binary shape of ``occupancy`` (``grid.shape``): :attr:`threshold`, or with
        ``"volume"`` the level that encloses the volume measured by ``data``."""
        if self.threshold != "volume":
            return self.threshold
        if data is None:
            raise ValueError("threshold='volume' needs the data term (the measured volume)")
        return level_for_volume(occupancy, grid, self._volume(data), VOLUME_LEVELS)

    @staticmethod
    def _volume(data: DataTerm) -> float:
        """The volume (mm^3) the data measure: the robust mean of the profiles' totals over the gain."""
        return robust_volume(data.target.detach().cpu())[0] / data.gain
