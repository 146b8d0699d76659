"""Mesh files of a run: a surface written as PLY, STL or OBJ (the format follows the suffix)."""

from __future__ import annotations

from pathlib import Path

import trimesh

MESH_SUFFIXES = (".ply", ".stl", ".obj")


def save_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write ``mesh`` to ``path``; the format follows the suffix (``.ply``, ``.stl``, ``.obj``)."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {path.suffix!r}; use one of {MESH_SUFFIXES}")
    mesh.export(path, file_type=path.suffix.lower()[1:])
    return path
