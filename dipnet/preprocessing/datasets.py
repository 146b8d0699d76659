"""The data dipnet carries: example meshes and the authors' real recording.

Everything lives in the package folder ``dipnet/data`` (shipped as package data, so an installed
dipnet finds it outside the repository):

- ``meshes/``: 16 closed triangle meshes (animals, statues, CAD parts with holes) in their own
  units, with ``LICENSES.md`` (licence and attribution of each) and ``meshes.csv`` (faces, volume,
  extent, genus);
- ``real/3cats_fixture_3mm.csv``: the authors' real three-cats recording (Aberman et al. 2017,
  repository Kewiee/DipTransform), with ``README.md`` saying what is known about it.

In Hydra configs the folder is reachable as ``${dipnet_data:meshes/bunny.ply}`` (:mod:`dipnet.jobs.resolvers`).
"""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
MESHES_DIR = DATA_DIR / "meshes"
CATS_CSV = DATA_DIR / "real" / "3cats_fixture_3mm.csv"


def data_path(relative: str | Path = "") -> Path:
    """The absolute path of ``relative`` inside the bundled data folder.

    Raises:
        FileNotFoundError: naming the path and what the folder holds, when it does not exist.
    """
    path = DATA_DIR / relative
    if not path.exists():
        held = ", ".join(sorted(p.name for p in DATA_DIR.iterdir()))
        raise FileNotFoundError(f"no bundled data file {relative!s} (dipnet/data holds: {held})")
    return path


def mesh_names() -> list[str]:
    """The stems of the bundled meshes, sorted (``["boot", "bracket_B66", ...]``)."""
    return sorted(p.stem for p in MESHES_DIR.glob("*.ply"))


def check_mesh_names(names: list[str]) -> None:
    """Raise ``FileNotFoundError`` naming every one of ``names`` that is not a bundled mesh (and the bundled
    ones): a benchmark checks its ``--meshes`` before the first mesh's work, not when it reaches the name.

    Raises:
        FileNotFoundError: a name that is not a bundled mesh.
    """
    unknown = [name for name in names if not (MESHES_DIR / f"{name}.ply").is_file()]
    if unknown:
        raise FileNotFoundError(f"no bundled mesh {', '.join(map(repr, unknown))}; bundled: {', '.join(mesh_names())}")


def mesh_path(name: str) -> Path:
    """The bundled mesh ``name`` (a file stem such as ``"bunny"``).

    Raises:
        FileNotFoundError: listing the bundled names when ``name`` is not one of them.
    """
    check_mesh_names([name])
    return MESHES_DIR / f"{name}.ply"
