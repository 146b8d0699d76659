"""scripts/bench_uncertainty.py: its per-case scores on known answers."""

from __future__ import annotations

import numpy as np
import pytest

from script_modules import load_script


def test_scores_of_a_perfect_and_of_a_blind_probability():
    bench = load_script("bench_uncertainty")
    truth = np.zeros((10, 10, 10), bool)
    truth[3:7, 3:7, 3:7] = True
    binary = truth.copy()
    binary[3, 3:7, 3:7] = False  # one wrong face
    perfect = bench.scores(truth.astype(float), (binary != truth).astype(float), binary, truth)
    assert perfect["brier"] == 0.0 and perfect["ece"] == 0.0 and perfect["top"] > 0 and perfect["deciles"][0] == 0
    blind = bench.scores(np.full(truth.shape, 0.5), np.full(truth.shape, 0.5), binary, truth)
    assert blind["brier"] == pytest.approx(0.25) and len(blind["deciles"]) == 10
