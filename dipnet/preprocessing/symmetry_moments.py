"""Does a declared symmetry fit the dips? A test from the profiles' moments alone.

The ``k``-th moment of the dip profile along a unit direction ``theta``,
``m_k(theta) = sum_j t_j^k p_j / sum_j p_j`` (``t_j`` the slab centres, mm, measured from the frame's origin), is a
homogeneous polynomial of degree ``k`` in ``theta``: ``m_1 = c . theta`` for the centroid ``c``, ``m_2`` the
object's second moments, and so on (the Helgason-Ludwig consistency conditions of the Radon transform; slabs of
thickness ``h`` add ``h^2 / 12`` to ``m_2``, the same along every direction). An object invariant under a group
``G`` about the origin has ``m_k(g theta) = m_k(theta)`` for every ``g`` in ``G``, so its moments are fitted
as well by the ``G``-invariant polynomials (the free fit's basis averaged over the group) as by all of them.

For each order ``k = 1, 2, 3`` both fits (each with a constant, which takes a start height or scale that all dips
share) are compared by an F test over the dips, and the misfit is put in the object's own scale: the root mean
square of what the invariant fit misses beyond the free fit, over ``k r_g^k`` for the object's radius of gyration
``r_g`` (material moved by a share ``s`` of ``r_g`` moves order ``k``'s moments by about ``k s r_g^k``, so every
order reads as a displacement). A declared symmetry is rejected when some order's misfit is both significant
(``p`` below :data:`P_LIMIT`) and larger than :data:`MISFIT_LIMIT`. On random scans of 23 shapes (8-80 dips,
noise-free to 20 dB, 32 voxels per axis: ``scripts/bench_symmetry_check.py``) no declaration an object has was
rejected (0 of 312 scans; where significant, its misfit stayed at or below 0.0014), and declarations it clearly
lacks (a noise-free misfit above 0.05) were rejected in 331 of 336 scans, the rest on 13-19 dips. Nearly
symmetric objects sit between (the penguin's left-right mirror, 0.0067, kept; the stuffed toy's, 0.010, rejected
in half the scans), and asymmetry that moves little material, such as a chamber inside a box off the mirror plane
(0.0023), stays below the limit: the moments weigh the bulk.

Dips whose profile is not a whole dip (truncated dips kept, interpolated directions) are left out
(:func:`whole_dips`); a symmetry's images are not dips either, so the top-level ``symmetry`` option is tested
before they are added (:func:`~dipnet.preprocessing.symmetry.expand_symmetry`). With too few dips left for an
order (fewer than 3 degrees of freedom: in 3D, order 3 needs 14) that order is not tested.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy import stats

from dipnet.core.measurement import DipMeasurement

#: A misfit this significant (the F test's p-value) is no noise.
P_LIMIT = 1e-3
#: A misfit (root mean square, relative to ``k r_g^k``) above this is more than a symmetric object's imperfection.
MISFIT_LIMIT = 0.01
#: The moment orders tested.
ORDERS = (1, 2, 3)
#: An order is tested with at least this many degrees of freedom left in its free fit.
MIN_DOF = 3


@dataclass
class SymmetryFit:
    """How well a symmetry group fits the dips' moments (:func:`symmetry_fit`).

    ``misfit`` and ``p_value``: those of the order whose misfit is the largest among the significant ones (else
    the largest misfit's); ``order`` that order (0 when no order could be tested, and then NaNs); ``dips``: the
    whole dips used; ``rejected``: ``p_value < P_LIMIT`` and ``misfit > MISFIT_LIMIT``.
    """

    misfit: float = float("nan")
    p_value: float = float("nan")
    order: int = 0
    dips: int = 0
    rejected: bool = False

    def metrics(self) -> dict:
        """The fields as a JSON-serialisable dict."""
        return asdict(self)

    @classmethod
    def from_metadata(cls, stored: Mapping) -> SymmetryFit:
        """The fit as :meth:`metrics` left it in a measurement's metadata (``None`` for NaN); other keys are
        ignored and missing ones keep their defaults (a hand-edited file)."""
        fit = cls()
        for name in (f.name for f in fields(cls)):
            if name in stored:
                value = stored[name]
                setattr(fit, name, float("nan") if value is None else type(getattr(fit, name))(value))
        return fit


def group_closure(generators: Sequence[np.ndarray], max_order: int = 240) -> np.ndarray:
    """Every element ``(G, d, d)`` of the group that the orthogonal ``generators`` (each ``(d, d)``) generate,
    the identity first; a ``ValueError`` when it has more than ``max_order`` elements (an irrational angle)."""
    gens = [np.asarray(g, dtype=np.float64) for g in generators]
    if not gens:
        raise ValueError("a symmetry group needs at least one generator")
    d = gens[0].shape[0]
    elements, frontier = [np.eye(d)], [np.eye(d)]
    while frontier:
        new = []
        for a in frontier:
            for g in gens:
                b = g @ a
                if not any(np.allclose(b, e, atol=1e-9) for e in elements):
                    elements.append(b)
                    new.append(b)
        if len(elements) > max_order:
            raise ValueError(f"the symmetry generators make a group of more than {max_order} elements")
        frontier = new
    return np.stack(elements)


def whole_dips(measurement: DipMeasurement) -> np.ndarray:
    """Indices ``(K',)`` of the dips whose profile is a whole measured dip: not truncated and kept
    (``metadata["recorded"]``), not an interpolated direction (those come last: ``interpolated_orientations``)."""
    meta = measurement.metadata or {}
    keep = np.ones(measurement.n_orientations, dtype=bool)
    recorded = meta.get("recorded") or {}
    if recorded.get("truncated_policy") == "keep":
        keep[np.asarray(recorded.get("truncated") or [], dtype=int)] = False
    interpolated = int(meta.get("interpolated_orientations") or 0)
    if interpolated:
        keep[-interpolated:] = False
    return np.flatnonzero(keep)


@dataclass
class WholeDipProfiles:
    """The whole dips of a measurement as the moment tests read them (:func:`whole_dip_profiles`): ``index``
    ``(K',)`` in the measurement, unit ``directions`` ``(K', d)``, ``profiles`` and their slab ``centres`` ``(K', M)``
    (mm^3 and mm), each profile's ``totals`` ``(K',)``, the ``offsets`` ``(K', M)`` of the centres from each
    profile's own centroid (mm), and the object's radius of gyration ``radius`` (mm, the root mean square offset)."""

    index: np.ndarray
    directions: np.ndarray
    profiles: np.ndarray
    centres: np.ndarray
    totals: np.ndarray
    offsets: np.ndarray
    radius: float


def whole_dip_profiles(measurement: DipMeasurement) -> WholeDipProfiles | None:
    """The whole dips of ``measurement`` (:func:`whole_dips`) for the moment tests; ``None`` when there is none, a
    profile holds no volume, or the profiles have no spread."""
    index = whole_dips(measurement)
    d = measurement.directions.double().numpy()[index]
    p = measurement.profiles.double().numpy()[index]
    totals = p.sum(1)
    if len(index) == 0 or not (totals > 0).all():
        return None
    t = measurement.slab_centres().numpy()[index]
    offsets = t - ((p * t).sum(1) / totals)[:, None]
    radius = math.sqrt(float(np.mean((p * offsets ** 2).sum(1) / totals)))
    if not radius > 0:
        return None
    return WholeDipProfiles(index=index, directions=d / np.linalg.norm(d, axis=1, keepdims=True), profiles=p,
                            centres=t, totals=totals, offsets=offsets, radius=radius)


def monomials(d: int, k: int) -> list[tuple[int, ...]]:
    """The exponents of the monomials of degree ``k`` in ``d`` variables."""
    return [a for a in itertools.product(range(k + 1), repeat=d) if sum(a) == k]


def monomial_design(directions: np.ndarray, exponents: list[tuple[int, ...]]) -> np.ndarray:
    """The monomials ``exponents`` of each row of ``directions`` ``(K, d)``: ``(K, len(exponents))``."""
    return np.stack([np.prod(directions ** np.asarray(a), axis=1) for a in exponents], axis=1)


def _order_test(directions: np.ndarray, moments: np.ndarray, group: np.ndarray, k: int) -> tuple[float, float]:
    """``(relative misfit before scaling, p-value)`` of order ``k``: NaNs when it cannot be tested."""
    n = len(directions)
    exponents = monomials(directions.shape[1], k)
    ones = np.ones((n, 1))
    free = np.hstack([monomial_design(directions, exponents), ones])
    invariant = np.hstack([np.mean([monomial_design(directions @ g.T, exponents) for g in group], axis=0), ones])
    rank_free, rank_inv = np.linalg.matrix_rank(free, 1e-8), np.linalg.matrix_rank(invariant, 1e-8)
    dof, extra = n - rank_free, rank_free - rank_inv
    if dof < MIN_DOF or extra < 1:
        return float("nan"), float("nan")
    rss_free = float(np.sum((moments - free @ np.linalg.lstsq(free, moments, rcond=None)[0]) ** 2))
    rss_inv = float(np.sum((moments - invariant @ np.linalg.lstsq(invariant, moments, rcond=None)[0]) ** 2))
    gain = max(rss_inv - rss_free, 0.0)
    p = float(stats.f.sf((gain / extra) / (rss_free / dof), extra, dof)) if rss_free > 0 else float(gain <= 0)
    return math.sqrt(gain / n), p


def symmetry_fit(measurement: DipMeasurement, group: np.ndarray) -> SymmetryFit:
    """Test the symmetry ``group`` ``(G, d, d)`` (orthogonal maps about the frame's origin, acting on
    ``(x, y[, z])``; :func:`group_closure`) against the whole dips of ``measurement`` (see the module docstring)."""
    dips = whole_dip_profiles(measurement)
    if dips is None:
        return SymmetryFit(dips=len(whole_dips(measurement)))
    d, p, t, totals, radius, index = dips.directions, dips.profiles, dips.centres, dips.totals, dips.radius, dips.index
    results = []
    for k in ORDERS:
        misfit, p_value = _order_test(d, (p * t ** k).sum(1) / totals, np.asarray(group, dtype=np.float64), k)
        if not math.isnan(misfit):
            results.append((misfit / (k * radius ** k), p_value, k))
    if not results:
        return SymmetryFit(dips=len(index))
    significant = [r for r in results if r[1] < P_LIMIT]
    misfit, p_value, k = max(significant or results)
    return SymmetryFit(misfit=misfit, p_value=p_value, order=k, dips=len(index),
                       rejected=bool(p_value < P_LIMIT and misfit > MISFIT_LIMIT))
