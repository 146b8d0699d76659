import math
import warnings

import numpy as np
import pytest
import torch

from dipnet.core import orientations as o
from dipnet.core.orientations import (
    Reach,
    check_grid_angles,
    direction_to_rig,
    fibonacci_hemisphere,
    reachable_candidates,
    rig_to_direction,
)

from planning_fixtures import reconstruct_cfg, tilt_spin


def test_fibonacci_hemisphere_is_unit_upper_and_uniform():
    v = o.fibonacci_hemisphere(400)
    assert v.shape == (400, 3)
    assert torch.allclose(v.norm(dim=1), torch.ones(400, dtype=torch.float64))
    assert bool((v[:, 2] > 0).all())
    # equal-area: the fraction of points above height z is 1 - z, and azimuths are balanced
    for z in (0.25, 0.5, 0.75):
        assert abs((v[:, 2] > z).double().mean().item() - (1 - z)) < 0.01
    assert v[:, :2].mean(0).norm() < 0.02


def test_random_hemisphere_is_seeded():
    a, b, c = o.random_hemisphere(50, 1), o.random_hemisphere(50, 1), o.random_hemisphere(50, 2)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert bool((a[:, 2] >= 0).all()) and torch.allclose(a.norm(dim=1), torch.ones(50, dtype=torch.float64))


def test_2d_angles_cover_half_turn():
    a = o.angles_2d(6)
    assert torch.allclose(a, torch.tensor([0, 30, 60, 90, 120, 150], dtype=torch.float64))
    d = o.directions_2d(a)
    assert torch.allclose(d[3], torch.tensor([0.0, 1.0], dtype=torch.float64), atol=1e-12)


def test_2d_angles_in_radians_are_warned_about():
    """Before: directions_2d(np.linspace(0, np.pi, 12, endpoint=False)) read the radians as degrees without a word:
    12 dips within 2.9 deg, a 24^2 elephant reconstructed (minnorm) at IoU 0.431 instead of 0.775."""
    with pytest.warns(UserWarning, match=r"all 12 angles lie within \[-2 pi, 2 pi\] \(0 to 2.88\).*np.degrees"):
        d = o.directions_2d(np.linspace(0, np.pi, 12, endpoint=False))
    assert torch.allclose(d[1], torch.tensor([math.cos(math.radians(math.pi / 12)),
                                              math.sin(math.radians(math.pi / 12))],
                                             dtype=torch.float64))  # still read as degrees, as documented
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        o.directions_2d(o.angles_2d(12))
        o.directions_2d([0.0, 3.0])  # two angles, or one: too few to tell
        o.make_directions("random", 40, 2, seed=3)


def test_paper_grid_matches_its_formula():
    v = o.paper_grid(3, 4)
    assert v.shape == (12, 3)
    t, p = math.radians(30), math.radians(90)
    assert torch.allclose(v[1 * 4 + 1], torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p),
                                                      math.cos(t)], dtype=torch.float64))


def test_rig_angles_to_directions():
    v = o.rig_to_direction([0, 90, 90, 30], [0, 0, 90, 45])
    assert torch.allclose(v[0], torch.tensor([0, 0, 1.0], dtype=torch.float64))
    assert torch.allclose(v[1], torch.tensor([1.0, 0, 0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(v[2], torch.tensor([0, -1.0, 0], dtype=torch.float64), atol=1e-12)
    # the tilt is the polar angle from the object's z axis, whatever the spin
    assert abs(math.degrees(math.acos(v[3, 2].item())) - 30) < 1e-9


@pytest.mark.parametrize("k", [0, -3, 2.5])
def test_bad_counts(k):
    with pytest.raises(ValueError):
        o.fibonacci_hemisphere(k)


def test_make_directions_names():
    assert o.make_directions("fibonacci", 10, 3).shape == (10, 3)
    assert o.make_directions("uniform", 10, 2).shape == (10, 2)
    with pytest.raises(ValueError, match="unknown orientation set"):
        o.make_directions("spiral", 10, 3)


@pytest.mark.parametrize("kind,k,ndim,error", [("randon", 4, 2, "unknown orientation set 'randon'"),
                                               ("random", 0, 2, "positive integer, got 0"),
                                               ("fibonacci", 3, 4, "2D and 3D, not 4D")])
def test_make_directions_refuses_in_2d_as_in_3d(kind, k, ndim, error):
    """Before: in 2D any name gave the equal angles (reconstruct.py ndim=2 orientations=randon: exit 0 on
    uniform dips), random with k=0 an empty (0, 2) set and ndim=4 Fibonacci 3D directions."""
    with pytest.raises(ValueError, match=error):
        o.make_directions(kind, k, ndim)
    assert o.make_directions("random", 4, 2, seed=1).shape == (4, 2)


def test_candidates_stay_within_the_rig_limits_and_cover_them():
    reach = Reach(tilt_range_deg=(10, 35), spin_range_deg=(0, 90), step_deg=5)
    tilt, spin = tilt_spin(reach.candidates())
    assert tilt.min() >= 10 - 1e-9 and tilt.max() <= 35 + 1e-9
    assert spin.min() >= -1e-9 and spin.max() <= 90 + 1e-9
    # every reachable direction lies within about one step of a candidate
    rng = np.random.default_rng(0)
    t, s = rng.uniform(10, 35, 500), rng.uniform(0, 90, 500)
    from dipnet.core.orientations import rig_to_direction
    probes = rig_to_direction(t, s).numpy()
    nearest = np.degrees(np.arccos(np.clip(probes @ reach.candidates().numpy().T, -1, 1))).min(axis=1)
    assert nearest.max() < 5.0
    assert bool(reach.contains(reach.uniform(30)).all())
    assert not bool(reach.contains(fibonacci_hemisphere(30)).all())


def test_presets_and_bad_limits():
    authors = reconstruct_cfg("reach=authors_rig").reach
    assert list(authors.tilt_range_deg) == [0.0, 35.0]
    assert len(reachable_candidates()) > len(reachable_candidates((0, 35)))
    with pytest.raises(ValueError, match="tilt range"):
        Reach(tilt_range_deg=(0, 120))
    with pytest.raises(ValueError, match="step"):
        Reach(step_deg=0)


@pytest.mark.parametrize("option, message", [
    ({"tilt_range_deg": [0, 35, 90]},
     r"reach.tilt_range_deg must be two numbers \[min, max\] \(degrees\), got \[0, 35, 90\]"),
    ({"tilt_range_deg": [True, 35]}, r"reach.tilt_range_deg must be two numbers .*, got \[True, 35\]"),
    ({"spin_range_deg": [0, "abc"]}, r"reach.spin_range_deg must be two numbers .*, got \[0, 'abc'\]"),
    ({"spin_range_deg": "09"}, r"reach.spin_range_deg must be two numbers"),  # was read as spins 0-9 deg
    ({"step_deg": True}, r"reach.step_deg must be a number of degrees, got True"),
])
def test_a_reach_of_the_wrong_shape_or_type_is_named(option, message):
    """Before: ``tilt_range_deg=[true, 35]`` was read as tilts 1-35 deg and ``step_deg=true`` as a 1 deg step,
    without a word; ``[0, 35, 90]`` failed as "too many values to unpack (expected 2)", naming no option."""
    with pytest.raises(ValueError, match=message):
        Reach(**option)
    assert Reach(tilt_range_deg=np.array([0, 35]), spin_range_deg=[0.0, 90], step_deg=5).tilt_range_deg == (0.0, 35.0)


@pytest.mark.parametrize("step", [0.3, 0.001, 1e-12])
def test_a_candidate_step_too_fine_to_enumerate_is_refused_by_name(step):
    """Before: ``reach.step_deg=0.001`` built ~2e10 rig angles (the job ran out of memory after minutes, no
    message); 0.3 deg built 230,000 candidates for the planner to score."""
    with pytest.raises(ValueError, match=r"reach .*step_deg.*: candidate step .* degrees gives .* candidate directions"
                                         r".* at most 100,000: give a larger step \(reach.step_deg\)"):
        Reach(step_deg=step)
    assert len(Reach(step_deg=1).candidates()) < o.MAX_CANDIDATES  # a 1 degree step is allowed
    assert len(Reach(tilt_range_deg=(0, 35), step_deg=0.3).candidates()) < o.MAX_CANDIDATES  # so is a fine one, small


def test_direction_rig_round_trip():
    tilt, spin = np.array([0.0, 10.0, 35.0, 80.0]), np.array([0.0, 20.0, 300.0, 123.0])
    t2, s2 = direction_to_rig(rig_to_direction(tilt, spin))
    assert np.allclose(t2, tilt) and np.allclose(s2[1:], spin[1:])


def test_grid_angles_outside_the_rigs_tilt_range_are_refused():
    """Before: ``tilts=[0,400]`` planned one dip, the 400 deg tilt dropped without a word."""
    check_grid_angles([0, 25, 50, 70], [0, 180], max_tilt_deg=90.0)
    check_grid_angles([0.0, 90.0], [-90, 400], max_tilt_deg=90.0)  # spins turn freely
    for tilts, spins, message in (
            ([0, 400], [0], r"tilts=\[0,400\]: 400 deg outside the rig's tilt range \[0, 90\] deg \(max_tilt_deg\)$"),
            ([0, 60], [0], r"60 deg outside the rig's tilt range \[0, 45\]"),
            ([-20], [0], r"-20 deg outside .*at spin \+ 180"),
            ([0, float("nan")], [0], r"nan is not a finite angle"),
            ([], [0], r"tilts must be a non-empty list"),
            ([0], None, r"spins must be a non-empty list"),
            ([0], ["abc"], r"spins=\['abc'\]: 'abc' is not a finite angle")):
        with pytest.raises(ValueError, match=message):
            check_grid_angles(tilts, spins, max_tilt_deg=45.0 if 60 in tilts else 90.0)


def test_a_grid_plan_refuses_a_tilt_the_rig_cannot_reach_instead_of_dropping_it():
    """plan_orientations (every caller, not only scan.py) refuses a grid tilt beyond max_tilt_deg."""
    from dipnet.rig.runner import plan_orientations

    assert plan_orientations("grid", tilts=[0, 30], spins=[0, 90], max_tilt_deg=60.0) == \
        [(0.0, 0.0), (0.0, 90.0), (30.0, 0.0), (30.0, 90.0)]
    with pytest.raises(ValueError, match="400 deg outside the rig's tilt range"):
        plan_orientations("grid", tilts=[0, 400], spins=[0])


def test_rig_angles_of_one_pose_are_kept_once():
    """Before: a grid with spins 0 and 360 dipped every tilt twice in one pose (minutes of robot time each, no
    new profile). Tilt 0 at other spins stays: on a rig whose tilt zero is off they are other directions."""
    pairs = [(t, s) for t in (0.0, 30.0) for s in (0.0, 360.0)]
    assert o.distinct_rig_angles(pairs) == ([(0.0, 0.0), (30.0, 0.0)],
                                            [((0.0, 360.0), (0.0, 0.0)), ((30.0, 360.0), (30.0, 0.0))])
    kept, repeats = o.distinct_rig_angles([(t, s) for t in (0, 25, 50, 70) for s in (0, 180)])  # scan.yaml's example
    assert len(kept) == 8 and repeats == []
    kept, repeats = o.distinct_rig_angles([(30, 0), (30, 0.0001), (30, 0.01), (90, 0), (90, 180), (30, -360),
                                           (30, 359.9999)])
    assert kept == [(30.0, 0.0), (30.0, 0.01), (90.0, 0.0), (90.0, 180.0)]  # 0.01 deg apart and d, -d are other dips
    assert repeats == [((30.0, 0.0001), (30.0, 0.0)), ((30.0, -360.0), (30.0, 0.0)), ((30.0, 359.9999), (30.0, 0.0))]
    assert o.distinct_rig_angles([]) == ([], [])


def test_the_unmeasured_wedge_of_2d_lines():
    """Line angles wrap at 180 deg (10 and 190 are one line); a 3D plan is refused. (No two gaps tie: which of two
    equal wedges comes first rests on round-off, which differs between numpy versions.)"""
    from dipnet.core.orientations import directions_2d, unmeasured_wedge_deg

    assert unmeasured_wedge_deg(directions_2d([10.0, 190.0, 120.0])) == pytest.approx((110.0, 10.0))
    assert unmeasured_wedge_deg(directions_2d([170.0, 20.0])) == pytest.approx((150.0, 20.0))
    with pytest.raises(ValueError, match=r"takes 2D directions \(K, 2\)"):
        unmeasured_wedge_deg(torch.eye(3))
