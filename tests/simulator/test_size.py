"""The simulator's size check: a mesh in the wrong units is refused before anything is allocated."""

import pytest

from dipnet.core.memory import MAX_READINGS_PER_DIP, ResourceError
from dipnet.shapes import Ball
from dipnet.simulator.size import check_simulation


def test_a_normal_simulation_is_estimated():
    estimate = check_simulation(Ball(30.0), n_dips=100, readings_per_dip=70, step_mm=1.0, available=10**12)
    assert estimate.parts["raw scan"] == 24.0 * 100 * 70 and estimate.total > estimate.parts["raw scan"]


def test_too_many_readings_per_dip_are_refused_with_the_fix():
    with pytest.raises(ResourceError, match=r"is the object in mm\? .*shape.radius=.*shape.scale="):
        check_simulation(Ball(3e7), n_dips=10, readings_per_dip=MAX_READINGS_PER_DIP + 1, step_mm=1.0,
                         available=10**15)


def test_more_memory_than_available_is_refused_naming_it():
    with pytest.raises(ResourceError, match="this machine has 1 KB available"):
        check_simulation(Ball(30.0), n_dips=100, readings_per_dip=70, step_mm=1.0, available=1000)
