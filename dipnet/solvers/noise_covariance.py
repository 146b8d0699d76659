"""The slabs' noise under a level sensor or balance: differences of cumulative readings.

A slab volume is the difference of the cumulative submerged volume at its two edges, each read with an
independent error, so neighbouring slabs' errors are anti-correlated (lag-1 correlation -1/2) and a profile's
low frequencies are known far better than independent slabs say. :func:`correlated_precision` gives the
inverse of that covariance (plus a white part, the model's own error) for the data terms that weigh
residuals by it: the solvers' ``noise_model="correlated"`` (:class:`~dipnet.solvers.optimize.DataTerm`) and
the surface refit (:mod:`dipnet.solvers.surface_refit`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from dipnet.core.measurement import filled_slabs

#: K x M x M precision entries a correlated noise model may hold (256 MB float32).
PRECISION_ENTRIES = 1 << 26


class ReadingsNoise(NamedTuple):
    """The precision of a profile set's slab errors and what the differenced noise alone scores under it."""

    precision: torch.Tensor  # (K, M, M) float64, mm^-6
    expected: float  # E[r^T P r] of the differenced noise: sum_k tr(P_k C_k)
    variance: float  # its variance: 2 sum_k tr((P_k C_k)^2) (Gaussian noise)


def filled_span(target: torch.Tensor, rel_tol: float = 0.005) -> torch.Tensor:
    """Boolean ``(K, M)``: the slabs from each profile's first to its last filled one (volume above
    ``rel_tol`` x the profile's largest), ends included."""
    filled = filled_slabs(target, rel_tol)
    return (torch.cumsum(filled.int(), dim=-1) > 0) & (torch.cumsum(filled.flip(-1).int(), dim=-1).flip(-1) > 0)


def correlated_precision(target: torch.Tensor, sigma: torch.Tensor, white_share: float = 1.0,
                         rel_tol: float = 0.005) -> ReadingsNoise:
    """The slabs' noise precision under the readings model, unnormalised.

    Over each profile's filled span (:func:`filled_span`; before it the baseline is exact, after it the
    readings repeat the total) the errors are differences of cumulative errors of variance ``sigma^2 / 2``
    plus a white part of variance ``white_share x sigma^2 / 2``; outside the span the slabs count as
    independent with variance ``sigma^2``.

    Args:
        target: measured slab volumes ``(K, M)``, mm^3.
        sigma: their noise sigma ``(K, M)``, mm^3 (each slab's sigma gives its upper edge's
            cumulative error ``sigma^2 / 2``).
        white_share: the white part's variance in units of ``sigma^2 / 2`` (> 0).
        rel_tol: see :func:`filled_span`.

    Returns:
        The precision ``(K, M, M)`` float64 (mm^-6), and the mean and variance of ``r^T P r`` for the
        differenced noise alone (``C_k`` its covariance, zero outside the span): ``sum_k tr(P_k C_k)`` and
        ``2 sum_k tr((P_k C_k)^2)``.

    Raises:
        ValueError: more than :data:`PRECISION_ENTRIES` entries.
    """
    k, m = target.shape
    if k * m * m > PRECISION_ENTRIES:
        raise ValueError(f"noise_model='correlated' holds a (K, M, M) = ({k}, {m}, {m}) precision, more than "
                         f"{PRECISION_ENTRIES:,} entries; use noise_model='independent' for a problem this large")
    var = sigma.double().pow(2).clamp(min=1e-300)
    span = filled_span(target, rel_tol)
    edge = torch.where(span, var / 2, torch.zeros_like(var))  # cumulative error at each slab's upper edge
    below = torch.cat([torch.zeros_like(edge[:, :1]), edge[:, :-1]], dim=1) * span  # and at its lower edge
    inside = span[:, 1:] & span[:, :-1]
    differenced = torch.diag_embed(edge + below) - torch.diag_embed(edge[:, :-1] * inside, offset=1) \
        - torch.diag_embed(edge[:, :-1] * inside, offset=-1)
    covariance = differenced + torch.diag_embed(torch.where(span, white_share * var / 2, var))
    precision = torch.linalg.inv(covariance)
    product = precision @ differenced
    return ReadingsNoise(precision, float(product.diagonal(dim1=-2, dim2=-1).sum()),
                         2.0 * float((product * product.transpose(-1, -2)).sum()))
