"""Closing a mesh's holes: one fan per boundary loop, oriented so the mesh becomes closed."""

import numpy as np
import trimesh

from dipnet.shapes.holes import boundary_caps


def _box_without(top: bool):
    """A 2 mm cube, without the two triangles of its top side when ``top``."""
    box = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    keep = box.face_normals[:, 2] < 0.5 if top else np.ones(len(box.faces), dtype=bool)
    return np.asarray(box.vertices), np.asarray(box.faces)[keep], box


def test_a_closed_mesh_has_no_caps():
    vertices, faces, _ = _box_without(False)
    caps, loops = boundary_caps(vertices, faces)
    assert loops == 0 and caps.shape == (0, 3, 3)


def test_a_missing_face_pair_is_closed_and_the_volume_restored():
    vertices, faces, box = _box_without(True)  # a square hole
    caps, loops = boundary_caps(vertices, faces)
    assert loops == 1 and caps.shape[1:] == (3, 3)
    closed = trimesh.util.concatenate([trimesh.Trimesh(vertices, faces, process=False),
                                       trimesh.Trimesh(caps.reshape(-1, 3), np.arange(caps.size // 3).reshape(-1, 3),
                                                       process=False)])
    closed.merge_vertices()
    assert closed.is_watertight and abs(closed.volume - box.volume) < 1e-9


def test_every_boundary_edge_is_used_once_each_way_after_capping():
    vertices, faces, _ = _box_without(True)
    caps, _ = boundary_caps(vertices, faces)
    boundary = {(a, b) for f in faces for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    index = {tuple(np.round(v, 9)): i for i, v in enumerate(vertices)}
    capped = [(index.get(tuple(np.round(t[i], 9))), index.get(tuple(np.round(t[(i + 1) % 3], 9))))
              for t in caps for i in range(3)]
    rim = [(a, b) for a, b in capped if a is not None and b is not None]
    assert rim and all((b, a) in boundary and (a, b) not in boundary for a, b in rim)
