"""The readings model's precision: what the differenced noise scores under it, in mean and variance."""

import numpy as np
import pytest
import torch

from dipnet.solvers.noise_covariance import PRECISION_ENTRIES, correlated_precision, filled_span


def profiles(k: int = 3, m: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab volumes ``(k, m)`` with empty slabs at both ends (a bump per profile) and their sigma."""
    t = torch.linspace(-1.5, 1.5, m, dtype=torch.float64)
    target = torch.stack([torch.clamp(1 - (t - 0.1 * i) ** 2, min=0) * (10 + i) for i in range(k)])
    return target, 0.2 + 0.05 * torch.rand(target.shape, generator=torch.Generator().manual_seed(0),
                                           dtype=torch.float64)


def test_filled_span_runs_from_the_first_to_the_last_filled_slab():
    target = torch.tensor([[0.0, 0.0, 1.0, 0.0, 2.0, 0.0], [3.0, 0.0, 0.0, 0.0, 0.0, 1.0]])
    assert filled_span(target).tolist() == [[False, False, True, True, True, False], [True] * 6]


@pytest.mark.parametrize("white_share", [1.0, 0.01])
def test_differenced_noise_scores_the_stated_mean_and_variance(white_share):
    """Cumulative readings' errors of variance sigma^2 / 2, differenced into slabs inside the filled span:
    ``r^T P r`` over 4000 draws has the mean and variance :func:`correlated_precision` states."""
    target, sigma = profiles()
    noise = correlated_precision(target, sigma, white_share)
    span = filled_span(target)
    gen = torch.Generator().manual_seed(1)
    edge = torch.randn((4000, *target.shape), generator=gen, dtype=torch.float64) * sigma / 2 ** 0.5 * span
    r = torch.diff(edge, dim=-1, prepend=torch.zeros_like(edge[..., :1])) * span  # none past the span
    scores = torch.einsum("skm,kmn,skn->s", r, noise.precision, r).numpy()
    assert np.mean(scores) == pytest.approx(noise.expected, rel=0.03)
    assert np.var(scores) == pytest.approx(noise.variance, rel=0.1)
    if white_share < 0.1:  # little white part: the differenced noise is nearly all the model's, one unit per slab
        assert noise.expected == pytest.approx(float(span.sum()), rel=0.05)
        assert noise.variance == pytest.approx(2 * float(span.sum()), rel=0.1)


def test_a_precision_larger_than_the_limit_is_refused():
    side = int((PRECISION_ENTRIES // 2) ** 0.5) + 1
    target, sigma = torch.ones(2, side), torch.ones(2, side)
    with pytest.raises(ValueError, match="noise_model='independent'"):
        correlated_precision(target, sigma)
