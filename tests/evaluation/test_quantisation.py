"""The sensor's reading quantum in a measurement (dipnet.evaluation.quantisation): its volume, the rounding's
sigma, the slabs an object spans and the finding that names a coarse sensor."""

from __future__ import annotations

import math

import pytest
import torch

from dipnet.core.measurement import DipMeasurement
from dipnet.evaluation.quantisation import (Quantum, centroid_allowance, coarse_quantum_message, object_slabs,
                                            reading_quantum)


def _measurement(metadata: dict) -> DipMeasurement:
    profiles = torch.tensor([[0.0, 0.0, 5.0, 10.0, 5.0, 0.0], [0.0, 4.0, 8.0, 8.0, 0.0, 0.0]], dtype=torch.float64)
    directions = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    return DipMeasurement(directions, profiles, 2.0, torch.zeros(2), metadata=metadata)


def test_the_quantum_is_read_from_the_metadata_when_recorded():
    quantum = reading_quantum(_measurement({"quantity": "level_mm", "reading_quantum": 0.5,
                                            "reading_quantum_volume": 30000.0}))
    assert quantum == Quantum(0.5, "mm", 30000.0, "level sensor")
    assert quantum.slab_sigma == pytest.approx(30000.0 * math.sqrt(2 / 12))  # two readings of variance q^2/12
    assert reading_quantum(_measurement({"quantity": "level_mm", "reading_quantum": None})) is None
    assert reading_quantum(_measurement({})) is None


def test_slabs_spanned_allowance_and_message():
    assert object_slabs(_measurement({}).profiles) == 3  # 3 slabs each (from the first to the last non-empty)
    assert centroid_allowance(Quantum(0.1, "mm", 6000.0, "level sensor"), 120000.0, 5.0, 10) == pytest.approx(1.25)
    level = coarse_quantum_message(Quantum(0.1, "mm", 6000.0, "level sensor"), 10900.0, "mm^3")
    assert level.startswith("the level sensor's resolution (0.1 mm = 6000 mm^3 per reading) is coarse against a "
                            "mean slab of 1.09e+04 mm^3 (a slab is 1.8 reading steps)")
    assert "use a finer sensor or thicker slabs" in level and level.endswith("a tank of smaller section")
    assert "tank" not in coarse_quantum_message(Quantum(5.0, "g", 5000.0, "balance"), 4000.0, "mm^3")
