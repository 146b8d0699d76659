"""Differentiable mesh dips against the numpy sweep, closed forms and finite differences."""

import numpy as np
import torch
import trimesh

from dipnet.operators.mesh_slabs import mesh_slab_volumes, mesh_volume_below
from dipnet.shapes import boundary_volume_below


def unit_directions(k: int, seed: int) -> torch.Tensor:
    v = torch.from_numpy(np.random.default_rng(seed).normal(size=(k, 3)))
    return v / v.norm(dim=1, keepdim=True)


def tensors(mesh: trimesh.Trimesh) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(mesh.vertices, dtype=torch.float64), torch.tensor(mesh.faces, dtype=torch.long)


def test_volume_below_matches_the_numpy_sweep_on_an_off_centre_mesh():
    mesh = trimesh.creation.icosphere(3, radius=10.0)
    mesh.vertices = mesh.vertices * [1.0, 0.6, 1.3] + [1.0, 2.0, -0.5]  # an ellipsoid: no symmetry to hide an error
    dirs = unit_directions(7, 0)
    heights = torch.linspace(-16, 16, 41).expand(7, -1)
    got = mesh_volume_below(*tensors(mesh), dirs, heights)
    expect = boundary_volume_below(mesh.vertices[mesh.faces], dirs.numpy(), heights.numpy())
    assert np.abs(got.numpy() - expect).max() < 1e-9 * mesh.volume
    assert torch.allclose(got[:, -1], torch.full((7,), mesh.volume, dtype=torch.float64), rtol=1e-12)
    assert float(got[:, 0].abs().max()) == 0.0


def test_slabs_of_an_axis_aligned_box_are_its_area_times_the_thickness():
    mesh = trimesh.creation.box(extents=(4.0, 6.0, 10.0))
    edges = torch.linspace(-6.0, 6.0, 13)  # 1 mm slabs; the box spans z in [-5, 5]
    slabs = mesh_slab_volumes(*tensors(mesh), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), edges)[0]
    expect = torch.where((edges[:-1] >= -5) & (edges[1:] <= 5), 24.0, 0.0).double()
    assert torch.allclose(slabs, expect, atol=1e-12)


def test_every_profile_sums_to_the_mesh_volume():
    mesh = trimesh.creation.torus(major_radius=6.0, minor_radius=2.0)
    slabs = mesh_slab_volumes(*tensors(mesh), unit_directions(5, 1), torch.linspace(-9, 9, 37))
    assert torch.allclose(slabs.sum(1), torch.full((5,), mesh.volume, dtype=torch.float64), rtol=1e-12)
    assert bool((slabs >= -1e-12).all())


def test_the_gradient_in_the_vertices_matches_finite_differences():
    mesh = trimesh.creation.icosphere(1, radius=3.0)
    vertices, faces = tensors(mesh)
    vertices = (vertices + 0.1 * torch.from_numpy(np.random.default_rng(2).normal(size=vertices.shape)))
    dirs, edges = unit_directions(3, 3), torch.linspace(-4, 4, 9)
    assert torch.autograd.gradcheck(lambda v: mesh_slab_volumes(v, faces, dirs, edges),
                                    (vertices.requires_grad_(True),), eps=1e-6, atol=1e-5)
