"""Do the dips agree with one object? Dips whose moments no object shares with the other dips.

The central moment of order ``k`` of the dip profile along a unit direction ``theta``,
``mu_k(theta) = sum_j (t_j - c)^k p_j / sum_j p_j`` (``c`` the profile's own centroid, so a dip's start height drops
out), is a homogeneous polynomial of degree ``k`` in ``theta`` for every object (the Helgason-Ludwig consistency
conditions of the Radon transform; the slabs' thickness adds lower even degrees, which ``|theta| = 1`` folds into
the same form, and a constant, fitted with it). Orders 2-4 are fitted over the dips by least squares. A dip whose
profile belongs to another direction than the one it is filed under (two rows swapped, an orientation log one
dip off) or to an object that has moved (slipped in its holder mid-scan) fits no polynomial the other dips fit.
The residual (studentized by the dip's leverage) is put in the object's own scale, over ``k r_g^k`` for its
radius of gyration ``r_g`` (as in :mod:`dipnet.preprocessing.symmetry_moments`: a displacement of material by
that share of ``r_g``), and set against what the readings' noise explains: a slab is the difference of two
cumulative readings, so the moment's error is ``sigma_r sqrt(sum_j (g_j - g_(j-1))^2)`` for the readings' noise
``sigma_r`` and the moment's derivative ``g_j`` with respect to slab ``j``.

A dip is an **outlier** when its residual exceeds :data:`OUTLIER_SIGMAS` of that noise and :data:`OUTLIER_SHARE` of
the object's scale. On 160 random correct scans (the 3D built-ins and the 16 bundled meshes in random orientations,
12-123 dips on the Fibonacci hemisphere or the authors' rig's 0-35 deg plan, 24^3 and 48^3 slabs, noise-free to
5 dB) no dip was an outlier; at 30 dB and cleaner a swapped pair of dips, a log one dip off from the middle on and
an object turned by 20 or 45 deg halfway were found in 69-88 % of the scans, at 5-15 dB in 0-42 %
(``scripts/bench_dip_agreement.py``, docs/benchmarks/dip-agreement.md). The authors' real recording of the cats
stays at half the share limit (0.026 at 6.2 sigmas).

Only whole dips of a 3D measurement are tested (:func:`~dipnet.preprocessing.symmetry_moments.whole_dips`); a
measurement holding a symmetry's images is not (they repeat its dips), nor an order whose fit leaves fewer than
:data:`MIN_DOF` degrees of freedom, nor a dip the fit hinges on (leverage above :data:`MAX_LEVERAGE`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dipnet.core.measurement import DipMeasurement, estimate_slab_sigma, reading_slab_sigma
from dipnet.preprocessing.symmetry_moments import monomial_design, monomials, whole_dip_profiles

#: The central-moment orders tested.
ORDERS = (2, 3, 4)
#: A dip's residual above this many noise sigmas (of its moment) ...
OUTLIER_SIGMAS = 8.0
#: ... and above this share of the object's scale (``k r_g^k``) makes it an outlier.
OUTLIER_SHARE = 0.05
#: An order is tested with at least this many degrees of freedom left in its fit.
MIN_DOF = 6
#: A dip whose leverage in an order's fit exceeds this is not judged by that order (the fit follows it).
MAX_LEVERAGE = 0.75


@dataclass
class DipAgreement:
    """The dips that disagree with the others (:func:`dip_agreement`).

    ``outliers``: their indices in the measurement (sorted); ``share`` and ``sigmas``: the largest outlier's
    residual in the object's scale and in noise sigmas, ``order`` its moment order (0 and NaNs with no outlier);
    ``tested``: the number of dips tested (0 when the measurement could not be).
    """

    outliers: list[int] = field(default_factory=list)
    share: float = float("nan")
    sigmas: float = float("nan")
    order: int = 0
    tested: int = 0


def reading_sigma(measurement: DipMeasurement) -> float:
    """The noise of one cumulative reading (mm^3): the readings' own scatter (preprocessing's metadata), else the
    stated per-slab sigma's median, else the profiles' estimate (:func:`estimate_slab_sigma`, an upper bound: it
    holds the profiles' curvature), each over ``sqrt(2)`` (a slab is the difference of two readings)."""
    slab = reading_slab_sigma(measurement.metadata or {})
    if slab is None:
        slab = (float(measurement.sigma.double().median()) if measurement.sigma is not None
                else estimate_slab_sigma(measurement.profiles))
    return slab / math.sqrt(2.0)


@dataclass
class DipScores:
    """Each tested dip's worst disagreement with the others (:func:`dip_scores`): ``index`` ``(T,)`` the dips'
    indices in the measurement; ``share`` and ``sigmas`` ``(T,)`` the residual in the object's scale and in noise
    sigmas of the order ``order`` ``(T,)`` nearest to or furthest beyond both limits."""

    index: np.ndarray
    share: np.ndarray
    sigmas: np.ndarray
    order: np.ndarray

    def outliers(self, share: float = OUTLIER_SHARE, sigmas: float = OUTLIER_SIGMAS) -> np.ndarray:
        """A mask ``(T,)`` of the dips beyond both limits."""
        return (self.share > share) & (self.sigmas > sigmas)


def dip_scores(measurement: DipMeasurement) -> DipScores | None:
    """Score every whole dip of ``measurement`` against the moments of the others (see the module docstring);
    ``None`` when the measurement cannot be tested (2D, symmetry images, an empty profile, no order testable).

    A dip that disagrees pulls the least-squares fit toward itself and makes dips that agree miss it too, so the
    worst outlier is set aside and the rest refitted, up to a third of the dips; each is then scored against the
    fit of the dips kept (by its prediction error, ``sqrt(1 + h)`` for its leverage ``h``)."""
    if measurement.ndim != 3 or "symmetry_group_order" in (measurement.metadata or {}):
        return None  # before whole_dip_profiles: an expansion's merged rows are not the truncated dips' indices
    dips = whole_dip_profiles(measurement)
    if dips is None:
        return None
    d, p, u, totals, radius, index = dips.directions, dips.profiles, dips.offsets, dips.totals, dips.radius, dips.index
    sigma_r = reading_sigma(measurement)
    fits = []
    for k in ORDERS:
        mu = (p * u ** k).sum(1) / totals
        below = (p * u ** (k - 1)).sum(1) / totals
        grad = (u ** k - mu[:, None] - k * below[:, None] * u) / totals[:, None]  # d mu_k / d p_j
        noise = sigma_r * np.sqrt((np.diff(np.pad(grad, ((0, 0), (1, 1))), axis=1) ** 2).sum(1))
        design = np.hstack([monomial_design(d, monomials(3, k)), np.ones((len(d), 1))])
        fits.append((k, mu, noise, design))
    kept = np.ones(len(index), dtype=bool)
    for _ in range(len(index) // 3):
        share, sigmas, _, judged = _scored(fits, kept, radius)
        beyond = np.where(kept & judged & (share > OUTLIER_SHARE) & (sigmas > OUTLIER_SIGMAS),
                          _beyond(share, sigmas), -np.inf)
        if not np.isfinite(beyond).any():
            break
        kept[int(np.argmax(beyond))] = False
    share, sigmas, order, judged = _scored(fits, kept, radius)
    if not judged.any():
        return None
    return DipScores(index=index[judged], share=share[judged], sigmas=sigmas[judged], order=order[judged])


def _scored(fits: list, kept: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(share, sigmas, order, judged)`` ``(K,)`` of every dip against the fits ``(k, mu, noise, design)`` of the
    dips ``kept``: per dip the order nearest to or furthest beyond both limits; ``judged``: some order scored it."""
    n = len(kept)
    share, sigmas = np.zeros(n), np.zeros(n)
    order, judged = np.zeros(n, dtype=int), np.zeros(n, dtype=bool)
    for k, mu, noise, design in fits:
        fitted = design[kept]
        if len(fitted) - np.linalg.matrix_rank(fitted, 1e-8) < MIN_DOF:
            continue
        residual = mu - design @ np.linalg.lstsq(fitted, mu[kept], rcond=None)[0]
        leverage = np.einsum("ij,jk,ik->i", design, np.linalg.pinv(fitted.T @ fitted), design)
        ok = ~kept | (leverage <= MAX_LEVERAGE)
        spread = np.sqrt(np.where(kept, 1.0 - np.clip(leverage, 0.0, MAX_LEVERAGE), 1.0 + leverage))
        scale = k * radius ** k
        r = np.abs(residual) / spread / scale
        z = r * scale / np.maximum(noise, 1e-300)
        worse = ok & (~judged | (_beyond(r, z) > _beyond(share, sigmas)))
        share[worse], sigmas[worse], order[worse] = r[worse], z[worse], k
        judged |= ok
    return share, sigmas, order, judged


def _beyond(share: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """How far beyond both limits (1 at the nearer one)."""
    return np.minimum(share / OUTLIER_SHARE, sigmas / OUTLIER_SIGMAS)


def dip_agreement(measurement: DipMeasurement) -> DipAgreement:
    """The dips of ``measurement`` that disagree with the others (see the module docstring)."""
    scores = dip_scores(measurement)
    if scores is None:
        return DipAgreement()
    out = scores.outliers()
    if not out.any():
        return DipAgreement(tested=len(scores.index))
    worst = int(np.argmax(np.where(out, _beyond(scores.share, scores.sigmas), -np.inf)))
    return DipAgreement(outliers=sorted(int(i) for i in scores.index[out]), share=float(scores.share[worst]),
                        sigmas=float(scores.sigmas[worst]), order=int(scores.order[worst]), tested=len(scores.index))
