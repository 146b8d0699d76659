import json

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement, MeasurementFileError, robust_volume
from dipnet.core.orientations import fibonacci_hemisphere


def _measurement(k=4, m=10, sigma=True):
    gen = torch.Generator().manual_seed(0)
    return DipMeasurement(directions=fibonacci_hemisphere(k),
                          profiles=torch.rand(k, m, generator=gen, dtype=torch.float64),
                          slab_thickness=2.5, offsets=torch.full((k,), -12.5),
                          sigma=torch.full((k, m), 0.1) if sigma else None, metadata={"source": "test"})


def test_save_load_round_trip(tmp_path):
    m = _measurement()
    back = DipMeasurement.load(m.save(tmp_path / "m.npz"))
    assert torch.equal(back.profiles, m.profiles) and torch.equal(back.directions, m.directions)
    assert torch.equal(back.sigma, m.sigma) and back.slab_thickness == 2.5 and back.metadata == {"source": "test"}
    assert DipMeasurement.load(_measurement(sigma=False).save(tmp_path / "n.npz")).sigma is None


def test_missing_and_corrupt_files_name_the_file(tmp_path):
    with pytest.raises(MeasurementFileError, match="not found"):
        DipMeasurement.load(tmp_path / "absent.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"this is not a zip file")
    with pytest.raises(MeasurementFileError, match="bad.npz"):
        DipMeasurement.load(bad)


def test_mismatched_shapes_are_reported(tmp_path):
    m = _measurement()
    path = m.save(tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays["profiles"] = arrays["profiles"][:3]
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match=r"m.npz.*profiles must have shape"):
        DipMeasurement.load(path)
    meta = json.loads(str(arrays["metadata"]))
    meta["version"] = 99
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match="version"):
        DipMeasurement.load(path)


@pytest.mark.parametrize("metadata", ["[1, 2]", '"x"', "3", "null"])
def test_metadata_that_is_no_json_object_names_the_file(metadata, tmp_path):
    path = _measurement().save(tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays["metadata"] = np.array(metadata)  # valid JSON, but no mapping (was: AttributeError from meta.get)
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match=r"m.npz: metadata must be a JSON object"):
        DipMeasurement.load(path)


PROVENANCE_EDITS = {"recorded": [1, 2], "readings": [1, 2], "level_drop": 5, "reach_mm": [[0.0, "x"]],
                    "outside_share": "abc", "reading_noise_volume": "x"}


@pytest.mark.parametrize("key", PROVENANCE_EDITS)
def test_provenance_of_another_form_is_refused_naming_the_file_and_entry(key, tmp_path):
    """A hand-edited provenance the job reads after the solve: was an AttributeError or TypeError traceback there
    (the result lost), or ``error: could not convert string to float: 'x'`` naming neither file nor entry."""
    m = _measurement()
    m.metadata = {"readings": {"readings_repaired": 0}, "level_drop": [[0.0, None]] * 4, "reach_mm": [[-3.0, 4.0]] * 4,
                  "outside_share": [0.0] * 4, "reading_noise_volume": None}
    path = m.save(tmp_path / "m.npz")
    assert DipMeasurement.load(path).metadata == m.metadata  # the forms the readers write
    m.metadata = {**m.metadata, key: PROVENANCE_EDITS[key]}
    with pytest.raises(MeasurementFileError, match=rf"m.npz: metadata provenance '{key}' must be "):
        DipMeasurement.load(m.save(path))


def test_resampling_keeps_volume_and_matches_on_same_edges():
    m = _measurement()
    same = m.resampled(m.offsets[0] + 2.5 * torch.arange(11, dtype=torch.float64))
    assert torch.allclose(same, m.profiles)
    coarse = m.resampled(torch.linspace(-20, 20, 6, dtype=torch.float64))
    assert torch.allclose(coarse.sum(1), m.profiles.sum(1))


def test_resampling_refuses_edges_that_do_not_increase():
    """Before: m.resampled(edges.flip(0)) returned every slab's volume negated (totals -2827.4 mm^2 for a 2827.4
    mm^2 disk) without a word, and a numpy array of edges failed with "'numpy.ndarray' object has no attribute
    'numpy'"."""
    m = _measurement()
    edges = torch.linspace(-20, 20, 6, dtype=torch.float64)
    with pytest.raises(MeasurementFileError, match=r"finite, increasing slab edges .* got 6 edges from 20 to -20 mm"):
        m.resampled(edges.flip(0))
    with pytest.raises(MeasurementFileError, match="increasing slab edges"):
        m.resampled(torch.tensor([0.0, float("nan"), 1.0]))
    torch.testing.assert_close(m.resampled(edges.numpy()), m.resampled(edges))
    assert torch.allclose(m.resampled(edges).sum(1), m.profiles.sum(1))


def test_numpy_views_with_negative_strides_make_a_measurement():
    """Before: DipMeasurement(np.eye(2)[::-1], profiles[:, ::-1], ...) failed with torch's "At least one stride in the
    given numpy array is negative"."""
    profiles = np.arange(8.0).reshape(2, 4)
    m = DipMeasurement(np.eye(2)[::-1], profiles[:, ::-1], 1.0, np.zeros(2)[::-1], sigma=np.ones((2, 4))[::-1])
    torch.testing.assert_close(m.profiles, torch.from_numpy(profiles).flip(1))
    torch.testing.assert_close(m.directions, torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=torch.float64))


def test_rebinning_round_trip_preserves_profile_totals(tmp_path):
    """A saved measurement re-bins onto any slab count: totals kept exactly, cumulative volumes
    kept at the common edges, and 10 -> 5 -> 10 slabs is exact where the coarse edges fall."""
    m = _measurement(m=10)  # slabs of 2.5 mm over [-12.5, 12.5]
    for n in (3, 5, 7, 24):
        edges = torch.linspace(-15.0, 15.0, n + 1, dtype=torch.float64)  # a wider grid, any count
        r = DipMeasurement.load(m.save(tmp_path / "m.npz")).rebinned(edges)
        assert r.profiles.shape == (4, n) and r.slab_thickness == pytest.approx(30.0 / n)
        torch.testing.assert_close(r.profiles.sum(1), m.profiles.sum(1))
        assert r.sigma.shape == (4, n) and r.metadata["rebinned_from"]["n_slabs"] == 10
    coarse = m.rebinned(torch.linspace(-12.5, 12.5, 6, dtype=torch.float64))
    torch.testing.assert_close(coarse.profiles, m.profiles.reshape(4, 5, 2).sum(2))
    # independent slabs
    torch.testing.assert_close(coarse.sigma, (0.1**2 * 2) ** 0.5 * torch.ones(4, 5, dtype=torch.float64))
    with pytest.warns(UserWarning, match="does not fit the grid"):
        m.rebinned(torch.linspace(-5.0, 5.0, 5, dtype=torch.float64))
    with pytest.raises(MeasurementFileError, match="uniform"):
        m.rebinned(torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64))


def test_recorded_source_reconstructs_a_saved_measurement_at_another_resolution(tmp_path):
    from dipnet.preprocessing.sources import read_recorded

    m = _measurement(m=10)
    path = m.save(tmp_path / "m.npz")
    r = read_recorded(str(path), Grid(16, 3, extent=30.0))
    assert r.profiles.shape == (4, 16)
    torch.testing.assert_close(r.profiles.sum(1), m.profiles.sum(1))


def test_robust_volume_ignores_outlying_totals():
    profiles = torch.full((20, 10), 10.0, dtype=torch.float64)
    profiles[:2] *= 0.3  # two truncated dips
    profiles[2:] += torch.linspace(-0.1, 0.1, 18, dtype=torch.float64)[:, None]
    volume, spread = robust_volume(profiles)
    assert volume == pytest.approx(100.0, rel=1e-3) and 0 < spread < 0.5


def test_a_measurement_without_dips_is_refused(tmp_path):
    m = _measurement()
    path = m.save(tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    for name in ("directions", "profiles", "offsets", "sigma"):
        arrays[name] = arrays[name][:0]
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match=r"m.npz.*at least 1 dip.*got 0"):
        DipMeasurement.load(path)


@pytest.mark.parametrize("name", ["profiles", "sigma", "offsets"])
def test_complex_arrays_are_refused_naming_the_file(tmp_path, name):
    """Complex ``profiles`` in a ``.npz`` were cast to real (their imaginary parts dropped) with only torch's
    warning."""
    path = _measurement().save(tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays[name] = arrays[name] + 1j * arrays[name]
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match=rf"^{path}: measurement array '{name}' holds complex numbers "
                                                   r"\(complex128\): a measurement's arrays are real"):
        DipMeasurement.load(path)
    with pytest.raises(MeasurementFileError, match="'profiles' holds complex numbers"):  # made in Python alike
        DipMeasurement(directions=fibonacci_hemisphere(4), profiles=torch.ones(4, 10, dtype=torch.complex128),
                       slab_thickness=2.5, offsets=torch.zeros(4))


def test_slab_centres_are_the_offsets_plus_half_a_slab_per_step():
    m = DipMeasurement(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), torch.ones(2, 3, dtype=torch.float64), 2.0,
                       torch.tensor([-3.0, 1.0], dtype=torch.float64))
    assert m.slab_centres().tolist() == [[-2.0, 0.0, 2.0], [2.0, 4.0, 6.0]]


def test_re_binning_recomputes_the_volume_beyond_the_slabs():
    """Before: a measurement re-binned onto narrower slabs (an .npz read on a smaller grid) kept the
    ``outside_share`` of its original slabs (0), so the consistency check read the volume the new slabs left out,
    which filled them to their ends, as a drifting level. Now it holds what the new slabs leave out, and
    ``outside_mm`` the readings' span beyond them."""
    profiles = torch.ones(2, 10)  # 10 mm slabs over [-50, 50] mm, 10 mm^3 each
    m = DipMeasurement(torch.eye(3)[:2], profiles, 10.0, torch.full((2,), -50.0),
                       metadata={"outside_share": [0.0, 0.5], "outside_mm": [0.0, 20.0]})
    narrow = m.rebinned(torch.linspace(-30.0, 30.0, 7, dtype=torch.float64), rel_tol=1.0)
    np.testing.assert_allclose(narrow.metadata["outside_share"], [0.4, 1 - 0.5 * 0.6])  # 4 of 10 slabs dropped
    np.testing.assert_allclose(narrow.metadata["outside_mm"], [40.0, 60.0])  # 100 mm of slabs, 60 mm kept
    wide = m.rebinned(torch.linspace(-60.0, 60.0, 13, dtype=torch.float64))
    np.testing.assert_allclose(wide.metadata["outside_share"], [0.0, 0.5])
    np.testing.assert_allclose(wide.metadata["outside_mm"], [0.0, 0.0])


def test_the_reach_is_read_from_the_slabs_and_kept_through_re_binning():
    """Without readings, the object reaches below the first non-empty slab's upper edge and above the last one's
    lower edge; re-binning keeps that rather than the wider span its interpolation spreads the volume over."""
    profiles = torch.zeros(1, 10)
    profiles[0, 2:7] = 5.0  # volume in [-30, 20] mm
    quiet = {"reading_noise_volume": 0.0}  # noise-free readings (unknown noise is estimated from the profiles)
    m = DipMeasurement(torch.eye(3)[2:], profiles, 10.0, torch.full((1,), -50.0), metadata=quiet)
    np.testing.assert_allclose(m.reach(), [[-20.0, 10.0]])
    smoothed = DipMeasurement(m.directions, m.profiles, 10.0, m.offsets, metadata={**quiet, "smoothed": True})
    np.testing.assert_allclose(smoothed.reach(), [[0.0, -10.0]])  # the 5-tap filter spreads two slabs on
    noisy = DipMeasurement(m.directions, m.profiles, 10.0, m.offsets, metadata={"reading_noise_volume": 1.0})
    np.testing.assert_allclose(noisy.reach(), [[np.nan, np.nan]])  # 5 mm^3 is within 5 sigmas of sqrt(2) mm^3
    coarse = m.rebinned(torch.linspace(-50.0, 50.0, 4, dtype=torch.float64))
    np.testing.assert_allclose(coarse.reach(), [[-20.0, 10.0]])
    np.testing.assert_allclose(DipMeasurement(m.directions, torch.zeros(1, 10), 10.0, m.offsets).reach(),
                               [[np.nan, np.nan]])


def test_directions_of_any_length_are_stored_as_unit_vectors():
    """A hand-built measurement's directions are lines, as the operators take them: rows scaled by 0.5 to 3 gave the
    same solve but a height trend of -12 mm pivot (0 with unit rows) and a limit of 26.6 mm instead of 1.7."""
    m = _measurement(k=6)
    scaled = DipMeasurement(m.directions * torch.linspace(0.5, 3.0, 6)[:, None], m.profiles, m.slab_thickness,
                            m.offsets, metadata={})
    assert torch.allclose(scaled.directions, m.directions, atol=1e-15)
    assert torch.equal(_measurement(k=6).directions, fibonacci_hemisphere(6))  # unit rows kept bit for bit


def test_slab_thickness_is_one_number():
    m = _measurement()
    for value in (torch.tensor(2.5), np.array([2.5]), np.float32(2.5)):
        same = DipMeasurement(m.directions, m.profiles, value, m.offsets)
        assert type(same.slab_thickness) is float and same.slab_thickness == 2.5
    for value in ("2.5", np.full(4, 2.5)):
        with pytest.raises(MeasurementFileError, match="slab_thickness must be one number of mm"):
            DipMeasurement(m.directions, m.profiles, value, m.offsets)


def test_metadata_is_a_dict_and_numpy_values_are_saved(tmp_path):
    m = _measurement()
    assert DipMeasurement(m.directions, m.profiles, 2.5, m.offsets, metadata=None).metadata == {}
    with pytest.raises(MeasurementFileError, match="metadata must be a dict"):
        DipMeasurement(m.directions, m.profiles, 2.5, m.offsets, metadata=["source"])
    m.metadata = {"snr_db": np.float32(20.0), "seed": np.int64(3), "centre": np.zeros(3), "scale": torch.tensor(2.0),
                  "mesh": tmp_path / "bunny.ply", "runs": [{"k": np.int32(4)}]}
    back = DipMeasurement.load(m.save(tmp_path / "m.npz")).metadata
    assert back == {"snr_db": 20.0, "seed": 3, "centre": [0.0, 0.0, 0.0], "scale": 2.0,
                    "mesh": str(tmp_path / "bunny.ply"), "runs": [{"k": 4}]}
    m.metadata = {"runs": [{"when": object()}]}
    with pytest.raises(MeasurementFileError, match=r"metadata\['runs'\]\[0\]\['when'\] holds a object"):
        m.save(tmp_path / "bad.npz")
    assert not (tmp_path / "bad.npz").exists()
    with pytest.raises(MeasurementFileError, match="is a folder: give the measurement file's name"):
        m.save(tmp_path)


def test_the_noise_of_two_slab_profiles_is_a_finite_upper_bound():
    """Profiles of 2 slabs have no [1, 2, 1] high-pass residual: the estimate was NaN (numpy's "Mean of empty
    slice"), so the consistency check's residual limit was null and a residual of 0.80 passed it unsaid."""
    import warnings

    from dipnet.core.measurement import estimate_slab_sigma

    profiles = torch.tensor([[10.0, 20.0], [12.0, 19.0], [11.0, 22.0]], dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sigma = estimate_slab_sigma(profiles)
    assert np.isfinite(sigma) and sigma > 0


def test_a_bare_npy_array_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "m.npz"
    with open(path, "wb") as fh:  # np.save to an open file keeps the name: an .npy array under a .npz name
        np.save(fh, np.ones((4, 10)))
    with pytest.raises(MeasurementFileError, match=r"m.npz: a single .npy array \(\(4, 10\) float64\), not a .npz"):
        DipMeasurement.load(path)  # was: TypeError: 'numpy.ndarray' object does not support the context manager


@pytest.mark.parametrize("value", [True, "2.5", None])
def test_a_slab_thickness_of_another_type_in_the_file_is_refused(value, tmp_path):
    path = _measurement().save(tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["metadata"]))
    if value is None:
        del meta["slab_thickness"]
    else:
        meta["slab_thickness"] = value  # was: float(True) = 1.0 mm read without a word, "2.5" read as 2.5
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)
    with pytest.raises(MeasurementFileError, match=r"m.npz: (slab_thickness must be one|metadata has no slab_t)"):
        DipMeasurement.load(path)
