"""Measurement sources: the recorded source reads once, checks, symmetrises once; file types; calibration input."""

import warnings
from functools import partial

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement, MeasurementFileError
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.preprocessing.sources import RecordedSource, finish_dips, read_recorded

GRID = Grid(16, 3, 100.0)


def _ball_measurement(k: int = 10, m: int = 16) -> DipMeasurement:
    """Dips of a ball of radius 30 mm centred at the origin: every profile is the same."""
    edges = np.linspace(-50.0, 50.0, m + 1)
    cum = np.pi * np.clip(30.0 + edges, 0, 60) ** 2 * (3 * 30.0 - np.clip(30.0 + edges, 0, 60)) / 3
    profile = np.diff(cum)
    return DipMeasurement(fibonacci_hemisphere(k), np.tile(profile, (k, 1)), edges[1] - edges[0],
                          np.full(k, edges[0]))


def test_finish_dips_checks_the_measured_dips_and_symmetrises_once(tmp_path):
    measured = _ball_measurement()
    finished, validation = finish_dips(measured, GRID, {"n_fold": 4})
    # consistent dips of one ball: nothing to warn about; the symmetry copies each of the 10 measured
    # directions to its 4 images about z (images within 0.5 deg merged)
    assert validation.warnings == [] and validation.metrics()["dips_rejected"] == 0
    assert finished.metadata["measured_orientations"] == 10
    assert 10 < finished.n_orientations <= 40
    assert torch.allclose(finished.profiles, measured.profiles[:1].expand(finished.n_orientations, -1))
    again, _ = finish_dips(measured, GRID, None)
    assert again is measured  # no symmetry: the measurement unchanged


def test_a_saved_measurement_is_read_rebinned_and_named(tmp_path):
    path = tmp_path / "m.npz"
    _ball_measurement(m=32).save(path)
    m = read_recorded(str(path), GRID, n_slabs=16)
    assert m.n_slabs == 16 and m.metadata["path"] == str(path)
    # re-binning keeps every profile's volume: the ball's 4/3 pi r^3
    assert torch.allclose(m.profiles.sum(dim=1), torch.full((10,), 4 / 3 * np.pi * 30.0**3, dtype=m.profiles.dtype))


def test_unknown_and_missing_files_are_named(tmp_path):
    with pytest.raises(MeasurementFileError, match="not found"):
        read_recorded(str(tmp_path / "none.npz"), GRID)
    (tmp_path / "m.txt").write_text("x")
    with pytest.raises(MeasurementFileError, match="unknown measurement file type '.txt'"):
        read_recorded(str(tmp_path / "m.txt"), GRID)


def test_file_types_are_told_by_their_suffix_in_any_case(tmp_path):
    """Before: a recording named ``.CSV`` (or ``.NPZ``) was refused as an unknown file type."""
    path = tmp_path / "M.NPZ"
    _ball_measurement(m=32).save(path)
    source = RecordedSource(partial(read_recorded, path=str(path)))
    assert source.extent_mm() == pytest.approx(100.0)
    assert source.measure(None, GRID, 16).measurement.n_slabs == 16
    upper = tmp_path / "CATS.CSV"
    upper.write_bytes(CATS_CSV.read_bytes())
    options = {"grid": Grid(16, 3, 360.0), "n_slabs": 16, "cross_section_mm2": 183600.0}
    read = read_recorded(str(upper), **options)
    assert torch.equal(read.profiles, read_recorded(str(CATS_CSV), **options).profiles)


def test_the_recorded_source_needs_a_reader_with_its_path():
    with pytest.raises(TypeError, match="path bound"):
        RecordedSource(read_recorded)


def test_the_recorded_source_refuses_a_mesh_before_anything_reads_it(tmp_path):
    # the job asks the source for the grid's extent first: a mesh must be named as the wrong file type there,
    # not reach "extent_mm is needed"
    (tmp_path / "bunny.ply").write_text("ply")
    with pytest.raises(MeasurementFileError, match="unknown measurement file type '.ply'.*shape=mesh"):
        RecordedSource(partial(read_recorded, path=str(tmp_path / "bunny.ply")))
    source = RecordedSource(partial(read_recorded, path=str(CATS_CSV)))
    assert source.path == CATS_CSV and source.truth() is None  # a real recording names no shape
    assert source.extent_mm() is None  # a raw recording has no slabs of its own


def test_the_recorded_source_measures_a_saved_measurement_and_its_extent(tmp_path):
    path = tmp_path / "m.npz"
    _ball_measurement().save(path)
    source = RecordedSource(partial(read_recorded, path=str(path)))
    assert source.extent_mm() == pytest.approx(100.0)
    acquired = source.measure(None, GRID, 16, symmetry={"n_fold": 2}, shape=None, seed=3)  # plan and seed unused
    assert acquired.raw is None and acquired.planning is None
    assert acquired.measurement.metadata["measured_orientations"] == 10


def test_self_calibration_input_needs_a_raw_recording_placed_by_the_geometry(tmp_path):
    path = tmp_path / "m.npz"
    _ball_measurement().save(path)
    with pytest.raises(ValueError, match="needs a raw recording"):
        RecordedSource(partial(read_recorded, path=str(path))).record(None, GRID, 16)
    with pytest.raises(ValueError, match="t_start"):
        RecordedSource(partial(read_recorded, path=str(CATS_CSV), t_start="centroid")).record(None, GRID, 16)


def test_the_cats_recording_is_prepared_for_calibration_with_the_readers_options():
    source = RecordedSource(partial(read_recorded, path=str(CATS_CSV), truncated="keep", smooth=False,
                                    geometry={"pivot_mm": 188.0}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        recording = source.record(None, GRID, 16, symmetry={"n_fold": 3, "mirror": True})
    assert len(recording.raw.orientations) == 32 and recording.initial.pivot_mm == 188.0
    assert recording.smooth is False and not recording.new
    assert recording.finish.keywords["symmetry"] == {"n_fold": 3, "mirror": True}
