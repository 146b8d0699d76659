"""Exact, differentiable dips of a closed triangle mesh: slab volumes as a function of its vertices.

The volume of ``{x . theta < h}`` inside a closed, outward-oriented surface is, by the divergence theorem
with ``F = (x . theta - h) theta`` (the derivation and the closed forms of ``J`` are those of
:mod:`dipnet.shapes.divergence`, which sweeps a fixed mesh in numpy):

    V(h) = sum over triangles S of (theta . n_S |S|) * J_S(h).

Here ``V`` is a torch function of the vertices, so a surface can be fitted to measured dips by gradient
descent (:mod:`dipnet.solvers.surface_refit`). Per direction, a triangle wholly below a plane adds
``w (mean - h)``, summed for all planes at once by a cumulative sum over the planes; only the (triangle,
plane) pairs whose plane cuts the triangle take the cubic closed form. A mesh of ``F`` triangles about a
slab thick costs ``O(K F)`` per evaluation.
"""

from __future__ import annotations

import torch

_DEN_FLOOR = 1e-30  # a cut triangle's denominators are positive; the floor guards the unused branch of `where`


def mesh_volume_below(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor,
                      heights: torch.Tensor) -> torch.Tensor:
    """Volume of a closed mesh below planes, differentiable in ``vertices``.

    Args:
        vertices: ``(V, 3)`` float64, mm (gradients flow to them).
        faces: ``(F, 3)`` long, counter-clockwise seen from outside (a watertight, outward-oriented mesh).
        directions: ``(K, 3)`` unit "up" vectors.
        heights: ``(K, E)`` plane heights per direction, ascending in each row, mm.

    Returns:
        ``(K, E)`` float64: the volume of ``{x . theta_k < h_kj}`` inside the mesh, mm^3.
    """
    tri = vertices[faces]                                               # (F, 3, 3)
    weight = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area vectors (F, 3)
    z = torch.einsum("fvd,kd->kfv", tri, directions)                     # vertex heights (K, F, 3)
    lo, mid, hi = torch.sort(z, dim=2).values.unbind(2)
    mean = z.mean(2)
    w = directions @ weight.T                                           # theta . n |S|, (K, F)
    n_dirs, n_faces = lo.shape
    n_heights = heights.shape[1]
    heights = heights.contiguous()
    with torch.no_grad():  # which planes lie above a triangle, and which cut it
        first_cut = torch.searchsorted(heights, lo.detach().contiguous(), right=True)
        first_above = torch.searchsorted(heights, hi.detach().contiguous(), right=True)
    # wholly below the planes j >= first_above: sum of w (mean - h_j) by cumulative sums over the planes
    below_wm = torch.zeros(n_dirs, n_heights + 1, dtype=vertices.dtype).scatter_add(1, first_above, w * mean)
    below_w = torch.zeros(n_dirs, n_heights + 1, dtype=vertices.dtype).scatter_add(1, first_above, w)
    volume = below_wm.cumsum(1)[:, :n_heights] - heights * below_w.cumsum(1)[:, :n_heights]
    # cut by the planes first_cut <= j < first_above
    counts = (first_above - first_cut).reshape(-1)
    pair = torch.repeat_interleave(torch.arange(n_dirs * n_faces), counts)
    plane = torch.arange(len(pair)) + (first_cut.reshape(-1) - (torch.cumsum(counts, 0) - counts))[pair]
    k = pair // n_faces
    h = heights[k, plane]
    dl, dm, dh = lo.reshape(-1)[pair], mid.reshape(-1)[pair], hi.reshape(-1)[pair]
    one_below = h <= dm
    j_one = -(h - dl) ** 3 / (3.0 * ((dm - dl) * (dh - dl)).clamp_min(_DEN_FLOOR))
    j_two = mean.reshape(-1)[pair] - h - (dh - h) ** 3 / (3.0 * ((dh - dl) * (dh - dm)).clamp_min(_DEN_FLOOR))
    cut = w.reshape(-1)[pair] * torch.where(one_below, j_one, j_two)
    return volume.reshape(-1).index_add(0, k * n_heights + plane, cut).reshape(n_dirs, n_heights)


def mesh_slab_volumes(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor,
                      edges: torch.Tensor) -> torch.Tensor:
    """Slab volumes of a closed mesh, differentiable in ``vertices``: the dip profiles an operator predicts.

    Args:
        vertices, faces, directions: as :func:`mesh_volume_below`.
        edges: slab boundaries, ``(M + 1,)`` shared by every direction or ``(K, M + 1)``, ascending, mm.

    Returns:
        ``(K, M)`` float64 slab volumes, mm^3.
    """
    if edges.ndim == 1:
        edges = edges.expand(directions.shape[0], -1)
    return torch.diff(mesh_volume_below(vertices, faces, directions, edges.to(vertices.dtype)), dim=1)
