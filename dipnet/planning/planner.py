"""Next-best-dip planning: which reachable orientation to dip next, given the dips so far.

Choice of criterion
-------------------
A dip along ``c`` measures the slab volumes ``A_c f``. Under the linearised Gaussian posterior
of :mod:`dipnet.evaluation.uncertainty` (prior variance on the reconstruction's boundary band, noise from
the data misfit) the information the dip brings is the mutual information between ``A_c f`` and
``f``, ``1/2 log det(I + A_c Sigma A_c^T / sigma^2)``. We score each candidate by its per-slab
version

    score(c) = sum_m log(1 + Var(a_{c,m}^T d) / sigma^2),

with the predicted slab variances taken from the posterior samples ``d_s`` (one sparse product
for all candidates). Why this and not the alternatives:

* A per-voxel variance map weighted by each profile's sensitivity (``sum_m a^T diag(v) a``)
  cannot tell directions apart: every plane family sums each voxel's variance once, so all
  candidates score the same up to boundary effects. The correlations in ``Sigma`` - which
  combinations of voxels the past dips left free - are what make one direction better, and
  samples keep them.
* The linear posterior alone (white prior) is the same for every object: it would only spread
  the dips evenly, which a Fibonacci plan already does. The boundary-band prior makes the
  score object-dependent: it favours planes tangent to the parts of the surface that are still
  unresolved, which is what errors in the binary shape are made of.
* The log keeps one very uncertain slab from outweighing a direction that informs many slabs
  (the full log-det would need an ``M x M`` determinant per candidate for little change).

Batches are chosen greedily: after each pick the samples' projections are conditioned on the
picked dip (an ensemble Kalman update in projection space, exact for the Gaussian samples up to
sampling error), so the next pick accounts for what the first will tell - this gives diversity
without any ad hoc angular penalty. Candidates come from :class:`dipnet.core.orientations.Reach`, so
a plan never leaves what the rig reaches.

``criterion="variance"`` scores by the expected reduction of the total posterior variance
instead (A-optimal, :func:`candidate_scores`); on the quick benchmark set (bunny and hammer, 32^3,
30 dB, minnorm planning) it gave a mean Chamfer of 0.0065 vs 0.0064 for the information score on
the hemisphere and 0.0451 vs 0.0388 under the 35 deg tilt limit, hence the default.

What a plan can gain, measured (32^3, 30 dB, voxel solver for every final reconstruction, six
meshes: bunny, part_B13, bracket_B66, fish, spot, hand; the settings of ``scripts/bench_planning.py
--n 32``, the alternative planners in a scratch copy of it that was not kept)
--------------------------------------------------------------------------------------------
* On the full hemisphere any well-spread plan of 41 dips is about as good as any other: the
  Fibonacci 41 plan rotated at random moves one mesh's Chamfer by about +-5% (bunny 0.0057 to
  0.0061), an object-blind farthest-point completion of the 8 initial dips is within 2% of Fibonacci,
  and even a cheating planner that dips where the current estimate's profiles differ most from
  the *true* ones does not beat it on the bunny (0.0060 vs 0.0057). Fibonacci 123 is 13% better
  than 41 in the mean: three times the data, which no choice of 41 directions replaces. What a
  choice of directions can win is alignment with large flat faces (bracket_B66: the one random
  rotation that put a dip along a face normal was 13% better than Fibonacci).
* Why the information score used to be flat: the noise variance is the misfit of the current
  estimate. With ``minnorm`` estimates in the loop that misfit is model error, 120x the sensor
  noise (bunny, 16 dips), so every candidate's predicted slab variance was far below it and the
  scores hardly differed (best 4.0, median 2.6 nats over 229 candidates). With the voxel solver
  in the loop - the best solver, also used for the final reconstruction - the misfit is the
  sensor noise and the scores spread (best 69, median 54, worst 21): the loop must reconstruct
  with the best solver. A posterior grid of half the reconstruction's resolution (blocks of
  2^3 voxels share one prior deviation, a crude model of a boundary that moves coherently)
  planned as well as the full one (mean Chamfer 0.00534 vs 0.00533) with 8x fewer unknowns.
* Tried and not kept (mean Chamfer over the six meshes, Fibonacci 41: 0.00539): profile
  sharpness of the estimate with an angular diversity kernel (0.0072 vs 0.0054 on the first
  four meshes: it clusters dips around the sharpest face); the same with a hard minimum
  separation (0.00539: faceted objects gain, smooth ones lose); 256 instead of 64 posterior
  samples (0.0055 vs 0.0053 on four meshes); the A-optimal score weighted by the flip density
  of each voxel (worse on the bunny, 0.0064 vs 0.0057).
* Kept: the information score with voxel-solver estimates and the half-resolution posterior,
  0.00534 (bracket_B66 0.0043 vs 0.0050, fish 0.0068 vs 0.0064): 1% better than Fibonacci 41
  in the mean, 14% worse than Fibonacci 123 (0.00470). No 41-dip plan we found reaches
  Fibonacci 123 on the hemisphere.
* Planners that know the answer (``scripts/bench_planning.py --oracle R --oracle-pool P``), a
  bound on what any planner can gain: the best of Fibonacci 41 and 12 random rotations of it, picked
  by Chamfer against the true shape, has mean Chamfer 0.0052 on the six meshes, 10% worse than
  Fibonacci 123 (worst over best rotation: 1.08 to 1.25 per mesh); a greedy planner that
  reconstructs each of 8 random candidates per dip and keeps the one with the lowest true
  Chamfer reaches 0.0050 on bunny, bracket_B66, part_B13 and hand against 0.0046 for Fibonacci
  123 (10% worse) and 0.0053 for this planner. Even with the true shape, 41 dips stay about 10%
  short of 123. Under the 35 deg tilt limit the same oracle gains 15% over the uniform cap plan on
  part_B13 (this planner 10%).
* All 16 bundled meshes at 64^3 (``scripts/bench_planning.py --jobs 2``): this planner against
  Fibonacci 41 0.958 (better on 10 meshes, worse by 2-6% on the smooth organic ones), against
  Fibonacci 123 1.274 (reached on the hollow cube only), under the tilt limit against the uniform
  cap plan 0.925 (better on 13 meshes).

Cost: the posterior (one Cholesky of ``(K M_c)^2``), one sparse product of the
samples with the candidates' matrix (built once per candidate set and cached) and ``k``
rank-``M_c`` updates of ``S x S`` size. Measured for a 64^3 reconstruction with 40 dips and a
32^3 posterior, a batch of 8 among 229 hemisphere candidates, one torch thread on 2 cores shared
with a load average of about 10: 10.5 s for the first step (building the candidates' matrix),
6.2 s for later ones; inside ``scripts/bench_planning.py --meshes fish part_B13`` (64^3,
voxel loop, load average 3-8) 2.0 s per step on average and at most 2.7 s.
"""

from __future__ import annotations

import inspect
import logging
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse
import torch

from dipnet.core.counts import is_real, whole_number
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import DipOperator, make_operator
from dipnet.core.reconstruction import Reconstruction
from dipnet.solvers.minnorm import operator_matrix
from dipnet.evaluation.resolvability import angle_to_plan
from dipnet.evaluation.uncertainty import Posterior, check_posterior_options, fit_posterior

log = logging.getLogger(__name__)

CRITERIA = ("information", "variance")
#: A candidate within this angle (deg) of a measured dip's line (``d`` or ``-d``: the same planes) is that dip again:
#: it measures no plane the data lack. The validation's duplicate-direction tolerance; candidates lie 5-10 deg apart.
MEASURED_DEG = 0.5


def measured_candidates(candidates: torch.Tensor, directions: torch.Tensor,
                        tol_deg: float = MEASURED_DEG) -> np.ndarray:
    """Boolean mask ``(C,)``: which ``candidates`` ``(C, 3)`` lie within ``tol_deg`` (deg) of the line of a measured
    direction ``(K, 3)`` (any length: normalised here), so that dipping them again measures the same planes."""
    c, d = (torch.nn.functional.normalize(torch.as_tensor(v, dtype=torch.float64), dim=1).numpy()
            for v in (candidates, directions))
    if not len(c) or not len(d):
        return np.zeros(len(c), dtype=bool)
    return np.degrees(angle_to_plan(c, d)) <= tol_deg


def repeated_directions(directions: torch.Tensor, tol_deg: float = MEASURED_DEG) -> np.ndarray:
    """Boolean mask ``(K,)``: which of the planned ``directions`` ``(K, 3)`` lie within ``tol_deg`` (deg) of the line of
    an earlier row (:func:`measured_candidates`), so that dipping them measures the same planes again (a reach of
    one direction, ``reach.tilt_range_deg=[0,0]``, makes every row of ``Reach.uniform`` the vertical)."""
    d = torch.as_tensor(directions, dtype=torch.float64)
    return np.array([i > 0 and bool(measured_candidates(d[i:i + 1], d[:i], tol_deg)[0]) for i in range(len(d))],
                    dtype=bool)


def unmeasured_lines(candidates: torch.Tensor, directions: torch.Tensor, tol_deg: float = MEASURED_DEG) -> int:
    """How many distinct lines (``c`` and ``-c``: the same planes) the ``candidates`` ``(C, 3)`` hold that no measured
    direction ``(K, 3)`` lies on (:func:`measured_candidates`): the most new dips a plan can add (a reach up to tilt
    90 deg holds both ``c`` and ``-c`` at that tilt)."""
    fresh = torch.as_tensor(candidates, dtype=torch.float64)[
        torch.from_numpy(~measured_candidates(candidates, directions, tol_deg))]
    return int((~repeated_directions(fresh, tol_deg)).sum())


def _keyword_defaults(function: Callable[..., Any]) -> dict[str, Any]:
    """The defaults of ``function``'s keyword-only arguments."""
    return {name: p.default for name, p in inspect.signature(function).parameters.items() if p.kind is p.KEYWORD_ONLY}


class Planner(ABC):
    """Chooses the next dips among candidate directions."""

    @abstractmethod
    def next(self, measurement: DipMeasurement, reconstruction: Reconstruction, candidates: torch.Tensor,
             k: int = 1, operator: DipOperator | None = None, posterior: Posterior | None = None) -> torch.Tensor:
        """The ``k`` next directions ``(k, 3)``, rows of ``candidates`` ``(C, 3)``, best first, none of them a
        direction ``measurement`` holds (:func:`measured_candidates`) nor two of them on one line; ``posterior``:
        :meth:`posterior` of the same reconstruction, if the caller has it already."""

    def posterior(self, reconstruction: Reconstruction, measurement: DipMeasurement,
                  operator: DipOperator | None = None) -> Posterior:
        """The linearised posterior around ``reconstruction`` (:func:`dipnet.evaluation.uncertainty.fit_posterior`)
        that the loop reports and this planner plans with, so that it is fitted once per step."""
        return fit_posterior(reconstruction, measurement, operator)

    def posterior_settings(self) -> dict[str, Any]:
        """How :meth:`posterior` is fitted (``planning.json``'s ``posterior``): the loop's uncertainty figures
        come from it, the job's ``metrics.json`` from ``output.uncertainty`` (its method and the job's seed)."""
        return {"method": "linearised", **_keyword_defaults(fit_posterior)}


def _number(name: str, value: Any) -> float:
    """``value`` (the planner option ``name``) as a float; ``ValueError`` naming it for a boolean or text (``true``
    was read as 1, ``"abc"`` failed as "could not convert string to float" naming no option)."""
    if not is_real(value):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return float(value)


class NextBestDipPlanner(Planner):
    """Greedy information-based planner (see the module docstring).

    Args:
        resolution: voxels per axis of the posterior grid.
        n_samples: posterior samples.
        band_voxels, floor: the boundary-band prior of :func:`dipnet.evaluation.uncertainty.fit_posterior`.
        seed: seed of the samples (fixed: the same dips give the same plan).
    """

    def __init__(self, resolution: int = 32, n_samples: int = 64, band_voxels: float = 1.5, floor: float = 0.05,
                 seed: int = 0, criterion: str = "information") -> None:
        if criterion not in CRITERIA:
            raise ValueError(f"unknown planning criterion {criterion!r}; choose one of {CRITERIA}")
        self.criterion = criterion
        self.options = {"resolution": whole_number("resolution", resolution),
                        "n_samples": whole_number("n_samples", n_samples),
                        "band_voxels": _number("band_voxels", band_voxels), "floor": _number("floor", floor),
                        "seed": whole_number("seed", seed, low=0)}
        check_posterior_options(self.options["resolution"], self.options["n_samples"], self.options["band_voxels"],
                                self.options["floor"])  # before the first dip, not after the initial ones
        self._cached: tuple[tuple, scipy.sparse.csr_matrix] | None = None
        self.last_seconds = 0.0

    def posterior(self, reconstruction: Reconstruction, measurement: DipMeasurement,
                  operator: DipOperator | None = None) -> Posterior:
        return fit_posterior(reconstruction, measurement, operator, **self.options)

    def posterior_settings(self) -> dict[str, Any]:
        return {**super().posterior_settings(), **self.options}

    def next(self, measurement: DipMeasurement, reconstruction: Reconstruction, candidates: torch.Tensor,
             k: int = 1, operator: DipOperator | None = None, posterior: Posterior | None = None) -> torch.Tensor:
        start = time.perf_counter()
        candidates = torch.as_tensor(candidates, dtype=torch.float64)
        if candidates.ndim != 2 or candidates.shape[1] != 3 or len(candidates) < k or k < 1:
            raise ValueError(f"need 1 <= k <= C candidates of shape (C, 3), got k={k}, {tuple(candidates.shape)}")
        measured = measured_candidates(candidates, measurement.directions)
        left = unmeasured_lines(candidates, measurement.directions)
        if k > left:
            raise ValueError(f"asked for {k} new dips, but only {left} of the {len(candidates)} candidates are not "
                             f"measured already (within {MEASURED_DEG:g} deg, or opposite another candidate): plan "
                             "fewer, or give more candidates (a finer reach step_deg)")
        if posterior is None:
            posterior = self.posterior(reconstruction, measurement, operator)
        projections = self._candidate_matrix(posterior.grid, posterior.n_slabs, candidates) @ posterior.samples.T
        chosen = greedy_batch(projections.T.reshape(len(posterior.samples), len(candidates), posterior.n_slabs),
                              posterior.noise_var, k, np.random.default_rng(self.options["seed"] + 1),
                              posterior.samples if self.criterion == "variance" else None, excluded=measured,
                              directions=candidates)
        self.last_seconds = time.perf_counter() - start
        log.info("planned %d dips among %d candidates in %.2f s", k, len(candidates), self.last_seconds)
        return candidates[chosen]

    def _candidate_matrix(self, grid, n_slabs: int, candidates: torch.Tensor) -> scipy.sparse.csr_matrix:
        key = (grid, n_slabs, candidates.numpy().tobytes())
        if self._cached is None or self._cached[0] != key:
            self._cached = (key, operator_matrix(make_operator(grid, candidates, n_slabs, backend="splat")))
        return self._cached[1]


def candidate_scores(projections: np.ndarray, noise_var: float, gram: np.ndarray | None = None) -> np.ndarray:
    """Score per candidate ``(C,)`` from sample projections ``(S, C, M)`` (centred).

    Without ``gram``: the information score ``sum_m log(1 + Var_s / sigma^2)``. With the samples'
    Gram matrix ``gram = D D^T`` ``(S, S)``: the expected reduction of the total posterior
    variance ``trace(C_dy (C_yy + sigma^2 I)^-1 C_dy^T)`` (A-optimal), with
    ``C_dy^T C_dy = Y^T (D D^T) Y / (S - 1)^2``.
    """
    n_samples, n_cand, n_slabs = projections.shape
    if gram is None:
        return np.log1p(projections.var(axis=0, ddof=1) / noise_var).sum(axis=1)
    y = projections.reshape(n_samples, -1)
    cyy = np.einsum("scm,scn->cmn", projections, projections) / (n_samples - 1) + noise_var * np.eye(n_slabs)
    cross = np.einsum("scm,scn->cmn", projections, (gram @ y).reshape(projections.shape)) / (n_samples - 1) ** 2
    return np.trace(np.linalg.solve(cyy, cross), axis1=1, axis2=2)


def greedy_batch(projections: np.ndarray, noise_var: float, k: int, rng: np.random.Generator,
                 samples: np.ndarray | None = None, excluded: np.ndarray | None = None,
                 directions: torch.Tensor | None = None) -> list[int]:
    """Pick ``k`` candidates one by one by :func:`candidate_scores`, conditioning on each pick; never a candidate
    of the boolean mask ``excluded`` ``(C,)`` (directions measured already), nor one twice, nor, given the candidates'
    ``directions`` ``(C, 3)``, one on the line of an earlier pick (:func:`measured_candidates`: its opposite measures
    the same planes, and with noisy data the conditioning alone hardly lowers its score).

    The conditioning is an ensemble Kalman update with perturbed observations; it acts on the
    samples from the left, ``D' = T D`` with ``T = I - E C_yy^-1 Y_c^T / (S - 1)`` ``(S, S)``, so
    the projections ``(S, C, M)`` and the Gram matrix of the samples ``(S, N)`` (A-optimal
    criterion, when ``samples`` is given) are updated without touching voxels.
    """
    n_samples, n_cand, n_slabs = projections.shape
    y = projections - projections.mean(axis=0, keepdims=True)
    gram = None
    if samples is not None:
        centred = samples - samples.mean(axis=0, keepdims=True)
        gram = centred @ centred.T
    chosen: list[int] = []
    excluded = np.zeros(n_cand, dtype=bool) if excluded is None else excluded.copy()
    for _ in range(k):
        scores = candidate_scores(y, noise_var, gram)
        scores[chosen] = -np.inf
        scores[excluded] = -np.inf
        best = int(np.argmax(scores))
        chosen.append(best)
        if directions is not None:
            excluded |= measured_candidates(directions, directions[best:best + 1])
        picked = y[:, best, :]  # (S, M)
        cov = picked.T @ picked / (n_samples - 1) + noise_var * np.eye(n_slabs)
        innovation = picked + rng.standard_normal(picked.shape) * np.sqrt(noise_var)
        transform = np.eye(n_samples) - innovation @ np.linalg.solve(cov, picked.T) / (n_samples - 1)
        y = (transform @ y.reshape(n_samples, -1)).reshape(y.shape)
        if gram is not None:
            gram = transform @ gram @ transform.T
    return chosen
