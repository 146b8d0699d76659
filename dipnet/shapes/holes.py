"""Caps over the holes of an open triangle mesh, so that its dips have a consistent volume.

The divergence-theorem dips (:mod:`dipnet.shapes.divergence`) are exact for a closed surface.
Through an open one they are a flux that depends on the height of the plane (the holes' area
vectors do not cancel), so the "submerged volume" can fall while the object goes down and
does not settle at the object's volume. Capping every boundary loop with a fan of triangles
around the loop's centroid closes the surface: the dips become a true volume (the caps are a
guess of the missing surface, so they stay approximate), whatever the hole's shape.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph


def boundary_caps(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Fan triangles closing every boundary loop of a mesh.

    Args:
        vertices: (V, 3) mm.
        faces: (F, 3) vertex indices, consistently oriented.

    Returns:
        ``(caps, loops)``: (C, 3, 3) triangles in mm, oriented against the boundary edges they
        close (so every boundary edge is then used once in each direction), and the number of
        boundary loops (connected components of boundary edges). Edges used by more than two
        faces are left as they are.
    """
    faces = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # (3F, 2) a -> b
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.ravel()] == 1]
    if len(boundary) == 0:
        return np.zeros((0, 3, 3)), 0
    n = len(vertices)
    graph = scipy.sparse.coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    on_loop = np.unique(boundary)
    loop_ids, loop_of = np.unique(label[on_loop], return_inverse=True)
    sums = np.zeros((len(loop_ids), 3))
    np.add.at(sums, loop_of, vertices[on_loop])
    centroid = sums / np.bincount(loop_of)[:, None]
    loop_index = np.searchsorted(loop_ids, label[boundary[:, 0]])
    v = np.asarray(vertices, dtype=np.float64)
    caps = np.stack([v[boundary[:, 1]], v[boundary[:, 0]], centroid[loop_index]], axis=1)
    return caps, len(loop_ids)
