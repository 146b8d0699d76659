"""Training pairs of the learned prior: the noise level, caching and value ranges."""

from __future__ import annotations

import numpy as np
import torch

from dipnet.experiments.prior_pairs import build_pairs, noisy_profiles


def test_noise_has_the_requested_snr_on_the_level_readings():
    profiles = torch.rand(4, 50, dtype=torch.float64) + 1
    noisy = noisy_profiles(profiles, 30.0, torch.Generator().manual_seed(0))
    cum, noise = torch.cumsum(profiles, -1), torch.cumsum(noisy - profiles, -1)
    snr = 20 * torch.log10(cum.pow(2).mean().sqrt() / noise.pow(2).mean().sqrt())
    assert abs(float(snr) - 30.0) < 1.0
    assert noisy_profiles(profiles, None, torch.Generator()) is profiles


def test_pairs_are_cached_and_bounded(tmp_path):
    x, y = build_pairs([5000, 5001], cache=tmp_path, n=16, dips=8, solver_options={"iterations": 10}, progress=False)
    assert x.shape == y.shape == (2, 16, 16, 16) and len(list(tmp_path.glob("pair_*.npz"))) == 2
    assert 0 <= x.min() and x.max() <= 1 and 0 <= y.min() and y.max() <= 1
    x2, _ = build_pairs([5000, 5001], cache=tmp_path, n=16, dips=8, solver_options={"iterations": 10}, progress=False)
    assert np.array_equal(x, x2)
