"""Robust readings: a spike is repaired back onto the curve, a clean dip is left alone, a noisy one rejected."""

import numpy as np
import pytest

from dipnet.core.rawscan import OrientationScan, RawScan, ScanHeader
from dipnet.preprocessing.readings import outlier_mask, repair_readings

STAGE = np.arange(40.0)
CURVE = 100.0 + 0.5 * np.clip(STAGE - 10.0, 0.0, 20.0)  # rest, a steady rise, the plateau


def _scan(*value_sets) -> RawScan:
    raw = RawScan(header=ScanHeader(quantity="level_mm", ndim=3, tank_cross_section_mm2=6e4, step_mm=1.0))
    for k, values in enumerate(value_sets):
        raw.orientations.append(OrientationScan(k=k, tilt_deg=0.0, spin_deg=0.0, stage_mm=STAGE.copy(),
                                                values=np.asarray(values, dtype=float), time_s=STAGE.copy(),
                                                complete=True))
    return raw


def test_a_clean_monotone_dip_has_no_outlier():
    mask, tolerance = outlier_mask(STAGE, CURVE)
    assert not mask.any() and (tolerance > 0).all()


def test_a_spike_is_found_and_repaired_by_its_neighbours():
    spiked = CURVE.copy()
    spiked[25] += 5.0
    with pytest.warns(UserWarning, match=r"repaired 1 outlier reading\(s\), rejected 0 dip"):
        repaired, report = repair_readings(_scan(spiked))
    assert report.to_json()["readings_repaired"] == 1 and report.repaired[0]["index"] == 25
    assert np.allclose(repaired.orientations[0].values, CURVE)  # linear between good readings: the curve itself


def test_a_dip_with_too_many_outliers_is_rejected():
    rng = np.random.default_rng(0)
    bad = CURVE.copy()
    bad[rng.choice(40, 8, replace=False)] += 50.0  # 20% of the readings, more than max_fraction
    with pytest.warns(UserWarning, match=r"rejected 1 dip"):
        repaired, report = repair_readings(_scan(CURVE, bad), max_fraction=0.1)
    assert [r["k"] for r in report.rejected] == [1]
    assert [o.k for o in repaired.orientations] == [0]
    assert report.to_json()["dips_rejected"] == 1


@pytest.mark.parametrize("at", [25, 33])
def test_a_fall_that_lasts_is_kept_and_a_spike_beside_it_still_repaired(at):
    """A level falling by 5 mm after stage ``at`` and staying down (water pouring into a cavity; at 33, on the
    plateau, the readings before it lie above the end's level) is physics, not a glitch: its readings are kept as
    read, while a spike elsewhere in the dip is still repaired."""
    flooding = CURVE - np.where(STAGE > at, 5.0, 0.0)
    flooding[12] += 5.0
    with pytest.warns(UserWarning, match=r"repaired 1 outlier reading\(s\)"):
        repaired, report = repair_readings(_scan(flooding))
    assert [r["index"] for r in report.repaired] == [12] and not report.rejected
    np.testing.assert_array_equal(repaired.orientations[0].values[13:], flooding[13:])


def _flag(raw: RawScan, stages) -> RawScan:
    """``raw`` with the readings at ``stages`` (mm) of its first dip flagged unstable."""
    first = raw.orientations[0]
    first.flags = [["unstable"] if s in stages else [] for s in first.stage_mm]
    return raw


@pytest.mark.parametrize("stages, rejected", [((14.0, 15.0), False),   # a 3 mm gap: 1.5 slabs of 2 mm, kept
                                             ((14.0, 15.0, 16.0), True),  # 4 mm: 2 slabs
                                             ((2.0, 3.0, 4.0, 5.0), False),  # before the rise: nothing lost
                                             ((32.0, 33.0, 34.0, 35.0), False)])  # on the plateau
def test_flagged_readings_are_counted_and_a_wide_gap_where_the_level_rises_rejects_the_dip(stages, rejected):
    """Flagged readings are left out by preprocessing, which interpolates across them: across more than
    1.5 slabs of the rise the slabs would be guesses, so the dip goes (before contact or under water it is kept)."""
    with pytest.warns(UserWarning, match=rf"left out {len(stages)} flagged reading\(s\), rejected {int(rejected)} dip"):
        repaired, report = repair_readings(_flag(_scan(CURVE, CURVE), stages), slab_mm=2.0)
    assert report.to_json()["readings_flagged"] == len(stages)
    assert report.flagged == [{"k": 0, "count": len(stages), "stage_mm": [min(stages), max(stages)]}]
    assert [o.k for o in repaired.orientations] == ([1] if rejected else [0, 1])
    if rejected:
        assert "readings flagged unstable leave a gap of 4 mm (stage 13-17 mm, 2 slabs)" in report.rejected[0]["reason"]


def test_flagged_readings_are_not_judged_without_a_slab():
    with pytest.warns(UserWarning, match=r"left out 5 flagged reading\(s\), rejected 0 dip"):
        repaired, report = repair_readings(_flag(_scan(CURVE), (14.0, 15.0, 16.0, 17.0, 18.0)))
    assert len(repaired.orientations) == 1 and report.to_json()["readings_flagged"] == 5
