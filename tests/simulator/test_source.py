"""The simulated source: dips along a plan, batches with their own noise streams, joined raw scans."""

from functools import partial

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.planning.plans import FixedPlan
from dipnet.shapes import builtin_shape
from dipnet.preprocessing.validation import MeasurementValidationError
from dipnet.simulator.physics import DipProtocol, LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.simulator.source import SimulatedDips, SimulatedSource, concatenate, merge_raw

GRID = Grid(16, 3, 100.0)
BALL = builtin_shape("ball", ndim=3, radius=30.0)
SIMULATE = partial(simulate_measurement, protocol=DipProtocol(step_mm=2.0))


def test_simulated_dips_keep_every_batch_and_renumber_the_raw_scan():
    dips = SimulatedDips(SIMULATE, BALL, GRID, 16, seed=0)
    first = dips(fibonacci_hemisphere(3))
    assert first.n_orientations == 3
    both = dips(fibonacci_hemisphere(5)[3:])
    assert both.n_orientations == 5 and torch.equal(both.profiles[:3], first.profiles)
    assert [o.k for o in dips.raw.orientations] == [0, 1, 2, 3, 4]
    # a ball: every dip measures its volume, 4/3 pi r^3
    assert torch.allclose(both.profiles.sum(dim=1), torch.full((5,), BALL.volume, dtype=both.profiles.dtype), rtol=1e-3)


def test_concatenate_refuses_other_slabs():
    a = SimulatedDips(SIMULATE, BALL, GRID, 16, seed=0)(fibonacci_hemisphere(2))
    b = SimulatedDips(SIMULATE, BALL, GRID, 8, seed=0)(fibonacci_hemisphere(2))
    assert concatenate(a, a).n_orientations == 4
    with pytest.raises(ValueError, match="slab count and thickness"):
        concatenate(a, b)


def test_merge_raw_appends_and_renumbers():
    dips = SimulatedDips(SIMULATE, BALL, GRID, 16, seed=0)
    dips(fibonacci_hemisphere(2))
    raw = dips.raw
    merged = merge_raw(raw, raw)
    assert [o.k for o in merged.orientations] == [0, 1, 2, 3] and len(raw.orientations) == 2


def test_the_simulated_source_measures_a_fixed_plan_like_the_simulator():
    source = SimulatedSource(SIMULATE)
    assert source.truth(lambda: BALL) is BALL and source.extent_mm() is None
    acquired = source.measure(FixedPlan("fibonacci", 6), GRID, 16, shape=BALL, seed=2, progress=False)
    raw, direct = SIMULATE(BALL, fibonacci_hemisphere(6), grid=GRID, n_slabs=16, seed=2, progress=False)
    assert torch.equal(acquired.measurement.profiles, direct.profiles)
    assert len(acquired.raw.orientations) == 6 and acquired.planning is None
    assert acquired.validation.warnings == []


def test_the_simulated_source_symmetrises_once_and_refuses_a_shape_outside_the_ball():
    source = SimulatedSource(SIMULATE)
    acquired = source.measure(FixedPlan("fibonacci", 6), GRID, 16, shape=BALL, progress=False,
                              symmetry={"n_fold": 2})
    assert acquired.measurement.metadata["measured_orientations"] == 6
    assert acquired.measurement.n_orientations > 6
    big = builtin_shape("ball", ndim=3, radius=60.0)
    with pytest.raises(ValueError, match="does not fit the working ball"):
        source.measure(FixedPlan("fibonacci", 6), GRID, 16, shape=big, progress=False)


def test_the_recording_for_self_calibration_is_the_new_raw_scan():
    recording = SimulatedSource(partial(SIMULATE, smooth=True)).record(FixedPlan("fibonacci", 4), GRID, 16,
                                                                       shape=BALL, progress=False)
    assert recording.new and recording.smooth and recording.finish is None and recording.initial is None
    assert len(recording.raw.orientations) == 4
    assert np.all(np.diff(recording.raw.orientations[0].values) >= -1e-12)  # the level only rises as it dips


def test_a_simulated_drift_that_wrecks_the_measurement_is_named_with_its_option():
    """A level sensor drifting 0.5 mm/s adds ~100 mm to every dip: the size check's "wrong units or scale" also
    names the drift's option, its rate and what it adds over a dip."""
    source = SimulatedSource(partial(simulate_measurement, sensor=LevelSensor(drift_mm_per_s=0.5),
                                     protocol=DipProtocol(step_mm=1.0)))
    with pytest.raises(MeasurementValidationError, match="wrong units or scale") as caught:
        source.measure(FixedPlan("fibonacci", 4), GRID, 16, shape=BALL, seed=0, progress=False)
    assert "source.simulator.sensor.drift_mm_per_s=0.5 (mm/s;" in str(caught.value)
    assert "likely cause is the simulated drift" in str(caught.value)
