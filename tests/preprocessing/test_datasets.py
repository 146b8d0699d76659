"""The bundled data: sixteen meshes and the cats recording, found by name; unknown names listed."""

import pytest

from dipnet.preprocessing.datasets import CATS_CSV, DATA_DIR, check_mesh_names, data_path, mesh_names, mesh_path


def test_the_bundled_meshes_and_recording_are_there():
    names = mesh_names()
    assert len(names) == 16 and names == sorted(names) and "bunny" in names
    assert mesh_path("bunny") == DATA_DIR / "meshes" / "bunny.ply" and mesh_path("bunny").is_file()
    assert CATS_CSV.is_file() and data_path("real/3cats_fixture_3mm.csv") == CATS_CSV


def test_unknown_names_are_refused_with_what_exists():
    with pytest.raises(FileNotFoundError, match="bundled: boot, "):
        mesh_path("dragon")
    with pytest.raises(FileNotFoundError, match=r"no bundled data file none\.txt \(dipnet/data holds: .*meshes"):
        data_path("none.txt")


def test_a_list_of_names_is_checked_whole():
    check_mesh_names(["bunny", "torus"])
    with pytest.raises(FileNotFoundError, match=r"^no bundled mesh 'dragon', 'teapot'; bundled: boot, "):
        check_mesh_names(["bunny", "dragon", "teapot"])
