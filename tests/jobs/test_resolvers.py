"""The ``${dipnet_data:...}`` resolver: bundled files by relative path, a clear error for others."""

import pytest
from omegaconf import OmegaConf

import dipnet  # noqa: F401 (registers the resolvers)
from dipnet.preprocessing.datasets import CATS_CSV, mesh_path


def test_bundled_files_resolve_to_their_absolute_paths():
    cfg = OmegaConf.create({"csv": "${dipnet_data:real/3cats_fixture_3mm.csv}",
                            "mesh": "${dipnet_data:meshes/bunny.ply}"})
    assert cfg.csv == str(CATS_CSV) and cfg.mesh == str(mesh_path("bunny"))


def test_a_file_not_bundled_is_named():
    cfg = OmegaConf.create({"missing": "${dipnet_data:meshes/none.ply}"})
    with pytest.raises(Exception, match="no bundled data file meshes/none.ply"):
        _ = cfg.missing
