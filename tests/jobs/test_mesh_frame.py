"""A mesh the user gives keeps its frame: the job computes centred, writes the mesh files back in
the file's frame and states the shift (``frame_offset_mm``) in metrics.json."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_module

from dipnet.jobs.pipeline import run
from dipnet.shapes.mesh import load_mesh

CENTRE = np.array([40.0, -25.0, 12.0])       # mm, far from the origin


@pytest.fixture()
def off_centre(tmp_path):
    path = tmp_path / "part.stl"
    trimesh.creation.box(extents=(30.0, 20.0, 16.0)).apply_translation(CENTRE).export(path)
    return path


def test_the_shape_is_centred_and_remembers_the_shift(off_centre):
    shape = load_mesh(off_centre)
    np.testing.assert_allclose(shape.frame_offset, CENTRE, atol=1e-9)
    np.testing.assert_allclose((shape.bounds()[0] + shape.bounds()[1]) / 2, 0.0, atol=1e-9)
    scaled = load_mesh(off_centre, scale=2.0)                      # the file frame in mm: units x scale
    np.testing.assert_allclose(scaled.frame_offset, 2 * CENTRE, atol=1e-9)
    assert not load_mesh(off_centre, center=False).frame_offset.any()


def test_mesh_files_of_a_job_line_up_with_the_users_file(off_centre, tmp_path):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "output.progress=false", "shape=mesh", f"shape.path={off_centre}", "resolution=16", "n_dips=24",
            "output.figures=false", "output.uncertainty=false", "output.resolvability=false"])
    result = run(cfg, tmp_path / "job")
    saved = json.loads((tmp_path / "job" / "metrics.json").read_text())
    np.testing.assert_allclose(saved["frame_offset_mm"], CENTRE, atol=1e-9)
    voxel = result.reconstruction.grid.voxel_size
    source = trimesh.load(off_centre)
    for name in ("truth.ply", "reconstruction.ply"):
        mesh = trimesh.load(tmp_path / "job" / name)
        np.testing.assert_allclose(mesh.bounds, source.bounds, atol=1.5 * voxel, err_msg=name)


def test_a_2d_job_states_the_files_axes_and_shift_of_its_silhouette(off_centre, tmp_path):
    """A silhouette along y lies in the file's (z, x) plane: metrics.json names those axes (``frame_axes``) and the
    shift, so the centred 2D result plus ``frame_offset_mm`` covers the part's z and x in the file; a run on the job's
    measurement.npz states the same."""
    overrides = ["output.progress=false", "ndim=2", "resolution=32", "output.figures=false",
                 "output.uncertainty=false", "output.resolvability=false"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides + [
            "shape=mesh", f"shape.path={off_centre}", "shape.axis=y", "n_dips=12"])
        again = compose(config_name="config", overrides=overrides + [
            "source=recorded", f"source.reader.path={tmp_path / 'job' / 'measurement.npz'}"])
    result = run(cfg, tmp_path / "job")
    saved = json.loads((tmp_path / "job" / "metrics.json").read_text())
    assert saved["frame_axes"] == "zx"
    grid = result.reconstruction.grid
    rows, cols = np.nonzero(result.reconstruction.binary)
    centres = grid.extent / grid.n * (np.stack([cols, rows], axis=1) + 0.5) - grid.extent / 2
    placed = centres + np.asarray(saved["frame_offset_mm"])
    source = trimesh.load(off_centre).bounds[:, [2, 0]]  # the file's z and x
    np.testing.assert_allclose([placed.min(0), placed.max(0)], source, atol=1.5 * grid.voxel_size)
    run(again, tmp_path / "again")
    stated = json.loads((tmp_path / "again" / "metrics.json").read_text())
    assert {k: stated[k] for k in ("frame_axes", "frame_offset_mm")} == {k: saved[k] for k in ("frame_axes",
                                                                                                "frame_offset_mm")}
