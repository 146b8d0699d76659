"""The dip-agreement check: dips filed under another dip's direction, or of an object that moved mid-scan, are
named; correct dips (simulated, noise-free and noisy, and the authors' real recording) are not."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dipnet.core.grid import Grid
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.preprocessing.dip_agreement import OUTLIER_SHARE, OUTLIER_SIGMAS, dip_agreement, dip_scores
from dipnet.preprocessing.sources import read_recorded
from dipnet.shapes import builtin_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement

GRID = Grid(24, 3, 106.67)
DIPS = 40


def _dipped(name: str = "chamber_box", snr_db: float | None = None, directions=None, seed: int = 3):
    directions = fibonacci_hemisphere(DIPS) if directions is None else directions
    return simulate_measurement(builtin_shape(name, 3, 45.0), directions, grid=GRID, progress=False, seed=seed,
                                sensor=LevelSensor(snr_db=snr_db, seed=seed))[1]


@pytest.fixture(scope="module")
def chamber_box():
    return _dipped()


def _swapped(measurement, pairs):
    directions = measurement.directions.clone()
    for i, j in pairs:
        directions[[i, j]] = directions[[j, i]]
    return replace(measurement, directions=directions)


@pytest.mark.parametrize("snr_db", [None, 30.0, 10.0])
def test_correct_dips_agree(snr_db):
    agreement = dip_agreement(_dipped(snr_db=snr_db))
    assert agreement.outliers == [] and agreement.tested == DIPS


@pytest.mark.parametrize("pairs", [[(0, 20)], [(0, 20), (2, 22)], [(3, 16)], [(3, 16), (9, 34)]])
def test_swapped_dips_are_named(chamber_box, pairs):
    """Pairs whose directions the box's moments tell apart (not every pair: ``bench_dip_agreement.py``)."""
    agreement = dip_agreement(_swapped(chamber_box, pairs))
    assert agreement.outliers == sorted(i for pair in pairs for i in pair)
    assert agreement.share > OUTLIER_SHARE and agreement.sigmas > OUTLIER_SIGMAS and agreement.order in (2, 3, 4)


def test_swapped_dips_of_a_ball_agree():
    """A centred ball measures the same profile along every direction: swapping two dips changes nothing."""
    agreement = dip_agreement(_swapped(_dipped("ball"), [(0, 20)]))
    assert agreement.outliers == [] and agreement.tested == DIPS


def test_a_log_one_dip_off_is_found(chamber_box):
    half = DIPS // 2
    d = chamber_box.directions
    assert dip_agreement(replace(chamber_box,
                                 directions=torch.cat([d[:half], d[half + 1:], d[half:half + 1]]))).outliers


def test_an_object_that_turned_in_its_holder_is_found():
    plan = torch.as_tensor(fibonacci_hemisphere(DIPS), dtype=torch.float64)
    turn = torch.as_tensor(Rotation.from_rotvec(np.radians(45.0) * np.array([1.0, 0.0, 0.0])).as_matrix())
    moved = torch.cat([plan[:DIPS // 2], plan[DIPS // 2:] @ turn.T])
    measurement = replace(_dipped(directions=moved), directions=plan)  # filed under the plan's directions
    assert dip_agreement(measurement).outliers


def test_scores_cover_every_whole_dip(chamber_box):
    scores = dip_scores(_swapped(chamber_box, [(0, 20)]))
    assert sorted(scores.index.tolist()) == list(range(DIPS))
    assert set(scores.index[scores.outliers()].tolist()) == {0, 20}
    assert (scores.share >= 0).all() and (scores.sigmas >= 0).all()


def test_the_authors_real_recording_agrees():
    measurement = read_recorded(str(CATS_CSV), Grid(40, 3, 360.0), cross_section_mm2=183600.0, t_start="geometry",
                                truncated="keep", smooth=True,
                                geometry={"pivot_mm": 188.0, "tilt_axis_offset_mm": -18.0})
    agreement = dip_agreement(measurement)
    assert agreement.outliers == [] and agreement.tested >= 12  # 16 whole dips; the fit hinges on a few


def test_what_cannot_be_tested_is_not(chamber_box):
    flat = simulate_measurement(builtin_shape("chamber_box", 2, 45.0), directions_2d(angles_2d(30)),
                                grid=Grid(48, 2, 106.67), progress=False)[1]
    assert dip_agreement(flat).tested == 0  # 2D
    images = replace(chamber_box, metadata={**chamber_box.metadata, "symmetry_group_order": 2})
    assert dip_agreement(images).tested == 0  # a symmetry's images repeat the dips
    assert dip_agreement(_dipped(directions=fibonacci_hemisphere(8))).tested == 0  # too few dips for any order


def test_images_whose_merges_renumber_the_rows_are_not_tested(chamber_box):
    """A symmetry expansion merges near directions, so its rows are no longer the recording's dips: the truncated
    dips' indices (``recorded.truncated``) may lie past them. Tilts read in radians as degrees (every dip within
    1 deg of the axis) merged the cats' 32 dips into 7 rows, and the check ended in an IndexError after the solve."""
    merged = replace(chamber_box, metadata={**chamber_box.metadata, "symmetry_group_order": 6,
                                            "recorded": {"truncated_policy": "keep", "truncated": [DIPS + 5]}})
    assert dip_agreement(merged).tested == 0
