"""Preprocessing raw scans into uniform slabs, on hand-built scans of a prism (analytic physics)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.operators import make_operator
from dipnet.preprocessing.preprocess import (check_stage_step, gausswin, preprocess, preprocess_file, slab_edges,
                                            smooth_profiles)
from dipnet.core.rawscan import OrientationScan, RawScan, ScanHeader

AREA = 60000.0  # tank cross-section, mm^2
A_PRISM, T0, T1 = 2000.0, -30.0, 30.0  # prism cross-section (mm^2) and extent along theta (mm)
T_START = -40.0
EDGES = np.linspace(-50.0, 50.0, 41)
VOLUME = A_PRISM * (T1 - T0)


def _prism_rise(stage: np.ndarray) -> np.ndarray:
    """Exact water rise for a prism: A delta = a (t_start + s + delta - t0), clipped."""
    partial = A_PRISM * (T_START + stage - T0) / (AREA - A_PRISM)
    return np.clip(partial, 0.0, VOLUME / AREA)


def _exact_slabs(edges: np.ndarray = EDGES) -> np.ndarray:
    lo, hi = np.maximum(edges[:-1], T0), np.minimum(edges[1:], T1)
    return A_PRISM * np.clip(hi - lo, 0.0, None)


def _scan(k: int = 1, sigma: float = 0.0, quantity: str = "level_mm", seed: int = 0, state: bool = True,
          **header) -> RawScan:
    stage = np.arange(0.0, 80.0, 1.0)
    rise = _prism_rise(stage)
    rng = np.random.default_rng(seed)
    head = ScanHeader(**{"quantity": quantity, "tank_cross_section_mm2": AREA, "step_mm": 1.0,
                         "t_start_mm": T_START, **header})
    scans = []
    for i in range(k):
        ideal = 150.0 + rise if quantity == "level_mm" else 1e-3 * AREA * rise
        values = ideal + rng.normal(0.0, sigma, stage.shape) if sigma else ideal
        meta = {"noise_sigma": sigma} if sigma and state else {}
        scans.append(OrientationScan(k=i, direction=[0.0, 0.0, 1.0], meta=meta, stage_mm=stage, values=values,
                                     time_s=2.0 * np.arange(len(stage)), complete=True))
    return RawScan(header=head, orientations=scans)


def test_prism_profiles_sum_and_layout():
    m = preprocess(_scan(), edges=EDGES)
    p = m.profiles[0].numpy()
    assert np.abs(p - _exact_slabs()).max() < 0.01 * VOLUME
    np.testing.assert_allclose(p[8:32], A_PRISM * 2.5, rtol=1e-9)  # linear parts are exact
    assert p.sum() == pytest.approx(VOLUME, rel=1e-12)
    assert m.slab_thickness == pytest.approx(2.5) and float(m.offsets[0]) == -50.0
    assert m.sigma is None and m.metadata["t_start_mm"] == [T_START]


def test_default_edges_are_the_operators():
    grid = Grid(16, 3, 100.0)
    op = make_operator(grid, np.array([[0.0, 0.0, 1.0]]), n_slabs=8)
    np.testing.assert_allclose(slab_edges(grid, 8), op.slab_edges().numpy())
    m = preprocess(_scan(), grid=grid, n_slabs=8)
    assert m.n_slabs == 8 and m.profiles.sum().item() == pytest.approx(VOLUME)


@pytest.mark.parametrize("n_slabs", [0, 7.5, True])
def test_a_slab_count_that_is_no_whole_number_of_two_or_more_is_named(n_slabs):
    """Before: preprocess(scan, grid=grid, n_slabs=0) failed with "IndexError: index 1 is out of bounds for axis 0
    with size 1", n_slabs=7.5 gave 7 slabs (and make_operator(grid, dirs, n_slabs=2.5) 2) without a word."""
    grid = Grid(16, 3, 100.0)
    with pytest.raises(ValueError, match=rf"n_slabs must be a whole number >= 2 \(slabs per profile\), got {n_slabs}"):
        preprocess(_scan(), grid=grid, n_slabs=n_slabs)
    with pytest.raises(ValueError, match="n_slabs must be a whole number >= 2"):
        make_operator(grid, np.array([[0.0, 0.0, 1.0]]), n_slabs=n_slabs)
    assert preprocess(_scan(), grid=grid, n_slabs=8.0).n_slabs == 8


def test_start_height_estimates():
    raw = _scan()
    ref = preprocess(raw, edges=EDGES).profiles
    centred = preprocess(raw, edges=EDGES, t_start="centroid", object_centre=[0.0, 0.0, 0.5 * (T0 + T1)])
    assert centred.metadata["t_start_mm"][0] == pytest.approx(T_START, abs=0.05)
    assert np.abs((centred.profiles - ref).numpy()).max() < 0.01 * VOLUME
    given = preprocess(raw, edges=EDGES, t_start=T_START)
    np.testing.assert_array_equal(given.profiles.numpy(), ref.numpy())
    onset = preprocess(raw, edges=EDGES, t_start="onset")  # contact at the lowest edge
    assert onset.metadata["t_start_mm"][0] - T_START == pytest.approx(EDGES[0] - T0, abs=1.0)
    assert onset.profiles[0, 0] > 0
    no_meta = _scan(t_start_mm=None)
    with pytest.raises(ValueError, match="t_start_mm"):
        preprocess(no_meta, edges=EDGES, t_start="metadata")
    auto = preprocess(no_meta, edges=EDGES)  # falls back to the centroid at the origin
    assert auto.metadata["t_start_mm"][0] == pytest.approx(T_START, abs=0.05)


@pytest.mark.parametrize("t_start", [float("nan"), float("inf"), "middle"])
def test_a_start_height_that_is_no_height_is_named(t_start):
    """Before: preprocess(scan, t_start=nan) (or inf) failed with "`x` must contain only finite values." from the
    interpolation; a number still places the profiles (t_start=-40 as the scan's own start)."""
    with pytest.raises(ValueError, match=r"t_start must be a finite number \(mm\) or one of \('auto'"):
        preprocess(_scan(), edges=EDGES, t_start=t_start)
    np.testing.assert_allclose(preprocess(_scan(), edges=EDGES, t_start=T_START).profiles.numpy(),
                               preprocess(_scan(), edges=EDGES).profiles.numpy())


@pytest.mark.parametrize("area,message", [(1e-300, "1e-300"), (-5.0, "-5.0"), (float("nan"), "nan"),
                                          (float("inf"), "inf")])
def test_a_cross_section_outside_any_tank_is_named(area, message):
    """Before: preprocess(scan, cross_section_mm2=1e-300) gave a 2827 mm^2 disk profiles totalling 9.4e-300 mm^2
    without a word (the
    range a calibration file's section must lie in was not applied here), -5 and nan said the section was
    "unknown", inf failed with "`x` must contain only finite values."."""
    with pytest.raises(ValueError, match=rf"tank cross-section {message} \(cross_section_mm2\) is outside "
                                         r"\[1, 1e\+08\] mm\^2 \(mm in 2D\): wrong units\?"):
        preprocess(_scan(), edges=EDGES, cross_section_mm2=area)
    assert preprocess(_scan(), edges=EDGES, cross_section_mm2=AREA).profiles.sum().item() == pytest.approx(VOLUME)


def test_flagged_and_repeated_readings():
    raw = _scan()
    ref = preprocess(raw, edges=EDGES).profiles
    o = raw.orientations[0]
    for stage, value, flags in [(30.5, 170.0, ["unstable"]), (31.0, o.values[31], [])]:  # spike + repeat
        o.stage_mm = np.append(o.stage_mm, stage)
        o.values = np.append(o.values, value)
        o.time_s = np.append(o.time_s, 500.0)
        o.flags.append(flags)
    np.testing.assert_allclose(preprocess(raw, edges=EDGES).profiles.numpy(), ref.numpy(), rtol=1e-12)


def test_balance_scan_gives_the_same_profiles():
    level = preprocess(_scan(), edges=EDGES).profiles
    mass = preprocess(_scan(quantity="mass_g"), edges=EDGES).profiles
    np.testing.assert_allclose(mass.numpy(), level.numpy(), rtol=1e-9, atol=1e-6)


def test_noise_monotone_output_and_sigma():
    sigma_r = 0.005
    raw = _scan(k=300, sigma=sigma_r, seed=1)
    m = preprocess(raw, edges=EDGES)
    assert (m.profiles >= 0).all()
    predicted = np.sqrt(2.0) * AREA * sigma_r
    np.testing.assert_allclose(m.sigma.numpy(), predicted, rtol=1e-12)
    inner = slice(10, 30)  # slabs well inside the prism (the monotone fit is inactive there)
    err = m.profiles.numpy()[:, inner] - _exact_slabs()[inner]
    assert abs(err.mean()) < 0.1 * predicted
    assert err.std(axis=0).mean() == pytest.approx(predicted, rel=0.25)
    smoothed = preprocess(raw, edges=EDGES, smooth=True)
    assert (smoothed.sigma < m.sigma).all()
    serr = smoothed.profiles.numpy()[:, inner] - _exact_slabs()[inner]
    assert serr.std(axis=0).mean() == pytest.approx(smoothed.sigma[0, inner].mean().item(), rel=0.25)
    np.testing.assert_allclose(smoothed.profiles.sum(1).numpy(), m.profiles.sum(1).numpy(), rtol=1e-12)


def test_an_unstated_noise_is_measured_from_the_readings():
    """No dip states its noise: ``metadata["readings_slab_sigma"]`` is the per-slab sigma the readings' own
    scatter gives (what a stated noise would give, smoothed too); ``None`` when the noise is stated or the
    readings hold none (the prism's exact rise)."""
    sigma_r = 0.005
    stated = preprocess(_scan(k=40, sigma=sigma_r, seed=1), edges=EDGES)
    unstated = preprocess(_scan(k=40, sigma=sigma_r, seed=1, state=False), edges=EDGES)
    assert stated.metadata["readings_slab_sigma"] is None and unstated.sigma is None
    assert unstated.metadata["reading_noise_leak"] < 2
    assert unstated.metadata["readings_slab_sigma"] == pytest.approx(np.sqrt(2.0) * AREA * sigma_r, rel=0.1)
    smoothed = preprocess(_scan(k=40, sigma=sigma_r, seed=1), edges=EDGES, smooth=True)
    smoothed_unstated = preprocess(_scan(k=40, sigma=sigma_r, seed=1, state=False), edges=EDGES, smooth=True)
    assert smoothed_unstated.metadata["readings_slab_sigma"] == pytest.approx(
        float(smoothed.sigma[0, 20]), rel=0.1)
    assert preprocess(_scan(k=4), edges=EDGES).metadata["readings_slab_sigma"] is None


def test_quantum_enters_sigma():
    m = preprocess(_scan(sigma=0.003, resolution=0.01), edges=EDGES)
    expected = np.sqrt(2.0) * AREA * np.hypot(0.003, 0.01 / np.sqrt(12))
    np.testing.assert_allclose(m.sigma.numpy(), expected, rtol=1e-12)


def test_gausswin_and_volume_conserving_smoothing():
    np.testing.assert_allclose(gausswin(), [0.02193, 0.22851, 0.49912, 0.22851, 0.02193], atol=1e-5)
    p = np.zeros((2, 10))
    p[0, 0], p[0, 1], p[1, -1] = 5.0, 3.0, 7.0  # volume at the very ends
    s = smooth_profiles(p)
    np.testing.assert_allclose(s.sum(1), p.sum(1), rtol=1e-12)
    assert s[0, 2] > 0 and s[0, 0] < 5.0


def test_incomplete_orientations_and_errors():
    raw = _scan(k=2)
    raw.orientations[1].complete = False
    with pytest.warns(UserWarning, match="incomplete"):
        assert preprocess(raw, edges=EDGES).n_orientations == 1
    assert preprocess(raw, edges=EDGES, include_incomplete=True).n_orientations == 2
    raw.orientations[0].complete = False
    with pytest.raises(ValueError, match="holds no complete dip"), pytest.warns(UserWarning):
        preprocess(raw, edges=EDGES)
    with pytest.raises(ValueError, match="cross-section"):
        preprocess(_scan(tank_cross_section_mm2=None), edges=EDGES)
    with pytest.raises(ValueError, match="equally spaced"):
        preprocess(_scan(), edges=[0.0, 1.0, 3.0])
    with pytest.raises(ValueError, match="edges or the reconstruction grid"):
        preprocess(_scan())
    with pytest.raises(ValueError, match="t_start"):
        preprocess(_scan(), edges=EDGES, t_start="guess")


def test_preprocess_file(tmp_path):
    raw = _scan(k=2)
    path = raw.save(tmp_path / "scan.jsonl")
    m = preprocess_file(path, edges=EDGES, smooth=True)
    np.testing.assert_allclose(m.profiles.numpy(), preprocess(raw, edges=EDGES, smooth=True).profiles.numpy())
    assert m.metadata["rawscan"] == str(path) and m.metadata["orientation_k"] == [0, 1]


def test_a_stage_step_coarser_than_the_slabs_is_refused_or_warned():
    """The audit's cases: a 50 mm step on 6 mm slabs, and a mesh in metres (0.04 mm across, 1 mm steps),
    gave IoU 0 with exit 0. A step over 4 slabs is refused, naming the metres mistake; over 1 slab, warned."""
    from dipnet.core.orientations import fibonacci_hemisphere
    from dipnet.shapes import Ball
    from dipnet.simulator.physics import DipProtocol, simulate_scan

    grid = Grid(16, 3, 100.0)  # slabs of 6.25 mm
    for step, outcome in ((50.0, "refused"), (10.0, "warned"), (2.0, "fine")):
        raw = simulate_scan(Ball(30.0), fibonacci_hemisphere(6), protocol=DipProtocol(step_mm=step), progress=False)
        if outcome == "refused":
            with pytest.raises(ValueError, match=r"step \(50 mm\) is 8 slabs thick.*shape.scale=1000"):
                preprocess(raw, grid=grid)
        elif outcome == "warned":
            with pytest.warns(UserWarning, match=r"step \(10 mm\) is 1.6 slabs thick"):
                preprocess(raw, grid=grid)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                assert preprocess(raw, grid=grid).n_orientations == 6


def test_the_stage_step_is_checked_by_itself_or_left_to_a_caller_that_did():
    """check_stage_step says what preprocess says of the step; preprocess(check_step=False) does not say it again
    (a calibration checks once, then preprocesses every trial geometry)."""
    from dipnet.core.orientations import fibonacci_hemisphere
    from dipnet.shapes import Ball
    from dipnet.simulator.physics import DipProtocol, simulate_scan

    grid = Grid(16, 3, 100.0)  # slabs of 6.25 mm
    raw = simulate_scan(Ball(30.0), fibonacci_hemisphere(6), protocol=DipProtocol(step_mm=10.0), progress=False)
    with pytest.warns(UserWarning, match=r"step \(10 mm\) is 1.6 slabs thick"):
        check_stage_step(raw, 6.25)
    with pytest.raises(ValueError, match=r"step \(10 mm\) is 8 slabs thick"):
        check_stage_step(raw, 1.25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert preprocess(raw, grid=grid, check_step=False).n_orientations == 6


def test_volume_beyond_the_slab_edges_is_recorded_and_warned_about():
    """The prism spans [-30, 30] mm; slabs over [-25, 25] mm leave out 5 mm at each end, a sixth of its volume:
    recorded per dip as ``outside_share`` (with the 31 mm of readings there, ``outside_mm``) and warned about
    once, naming the share, the slabs' range and extent_mm. Slabs over [-50, 50] mm hold it all and say nothing."""
    with pytest.warns(UserWarning, match=r"2 of 2 dips hold more than 1% of their volume outside the slabs "
                                         r"\[-25\.0, 25\.0\] mm \(up to 16\.7%.*extent_mm must grow") as caught:
        m = preprocess(_scan(k=2), edges=np.linspace(-25.0, 25.0, 21))
    assert sum("outside the slabs" in str(w.message) for w in caught) == 1
    np.testing.assert_allclose(m.metadata["outside_share"], [1 / 6, 1 / 6], atol=1e-3)
    np.testing.assert_allclose(m.metadata["outside_mm"], [31.0, 31.0], atol=1e-6)  # [-40, -25] and [25, 41] mm
    assert float(m.profiles[0].sum()) == pytest.approx(VOLUME * 5 / 6, rel=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        whole = preprocess(_scan(k=2), edges=EDGES)
    assert whole.metadata["outside_share"] == [0.0, 0.0] and whole.metadata["outside_mm"] == [0.0, 0.0]


def test_the_reach_comes_from_the_readings():
    """How far the object reaches, from the readings: some volume below the first reading beyond the tolerance
    and above the last short of the final volume by more, whatever the slabs (a ball of radius 30 mm, 1 mm
    steps: within a step of its ends); no rise gives NaN. Preprocessing records it per dip (the prism: 30 mm)."""
    from dipnet.preprocessing.preprocess import reach_from_readings

    heights = np.arange(-40.0, 41.0, 1.0)
    cap = np.clip(heights + 30.0, 0.0, 60.0)  # the ball's height under the water line
    low, high = reach_from_readings(heights, np.pi * (30.0 * cap**2 - cap**3 / 3), tol=1.0)
    assert -30.0 < low <= -29.0 and 29.0 <= high < 30.0
    assert np.isnan(reach_from_readings(heights, np.zeros_like(heights), tol=1.0)).all()
    for edges in (EDGES, np.linspace(-25.0, 25.0, 21)):  # the slabs play no part
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reach = np.asarray(preprocess(_scan(k=2), edges=edges).metadata["reach_mm"], dtype=float)
        assert reach.shape == (2, 2) and (reach[:, 0] > -30.0).all() and (reach[:, 0] <= -28.0).all()
        assert (reach[:, 1] >= 28.0).all() and (reach[:, 1] < 30.0).all()


def test_round_off_is_not_reach():
    """Noise-free readings give a tolerance of 0: a monotone fit that ends 5e-13 mm^2 short of its final volume
    must not count as volume above the water line. A 2D square dipped edge-on (``ndim=2 n_dips=2``: 0 and 90 deg)
    put its top 20 mm too high (51.6 for 31.6 mm) and was refused as reaching beyond the working ball."""
    from dipnet.core.grid import Grid
    from dipnet.core.orientations import directions_2d
    from dipnet.preprocessing.preprocess import reach_from_readings
    from dipnet.preprocessing.validation import validate_measurement
    from dipnet.shapes.builtin import builtin_shape
    from dipnet.simulator.simulate import simulate_measurement

    heights = np.arange(-40.0, 41.0, 1.0)
    volume = np.clip(heights + 30.0, 0.0, 60.0) * 50.0
    volume[heights > 30.0] = volume[-1]
    volume[-12:-6] -= 4.547e-13  # the round-off of the monotone fit
    assert reach_from_readings(heights, volume, tol=0.0) == (-29.0, 29.0)
    grid = Grid(24, 2, 109.091)
    raw, m = simulate_measurement(builtin_shape("chamber_box", 2, radius=45.0), directions_2d([0.0, 90.0]),
                                  grid=grid, progress=False)
    reach = np.asarray(m.metadata["reach_mm"])
    assert (np.abs(reach) < 32.0).all(), reach  # the square's half-diagonal along an axis: 31.8 mm
    validate_measurement(m, grid)
