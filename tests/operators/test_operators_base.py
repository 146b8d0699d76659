"""The interface every backend shares (dipnet.operators.base.DipOperator), on a toy backend whose linear map is
known in closed form: checks of directions and slabs, the working-ball mask, batching, the cumulative profile,
the scipy view, named errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.operators import BACKENDS, make_operator
from dipnet.operators.base import DipOperator


class MiddleSlab(DipOperator):
    """A toy backend: every orientation puts the whole voxel volume into the middle slab, ``A x = V(x) e_mid``."""

    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        out = volume.new_zeros(volume.shape[0], *self.profile_shape)
        out[:, :, self.n_slabs // 2] = volume.flatten(1).sum(1, keepdim=True) * self.grid.voxel_volume
        return out

    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        weight = profiles[:, :, self.n_slabs // 2].sum(1) * self.grid.voxel_volume  # (B,)
        return weight.reshape(-1, *([1] * self.grid.ndim)).expand(-1, *self.grid.shape).clone()


GRID = Grid(8, 3, extent=16.0)  # 2 mm voxels, working ball of radius 6 mm


def test_directions_are_normalised_and_the_slabs_cover_the_extent():
    op = MiddleSlab(GRID, torch.tensor([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]]), n_slabs=4)
    torch.testing.assert_close(op.directions, torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], dtype=torch.float64))
    assert op.directions.dtype == torch.float64
    assert (op.n_orientations, op.profile_shape, op.slab_thickness) == (2, (2, 4), 4.0)
    torch.testing.assert_close(op.slab_edges(), torch.tensor([-8.0, -4.0, 0.0, 4.0, 8.0], dtype=torch.float64))
    assert MiddleSlab(GRID, torch.ones(1, 3)).n_slabs == GRID.n  # default: one slab per voxel


@pytest.mark.parametrize("directions,n_slabs,message", [
    (torch.ones(2, 2), None, r"directions must have shape \(K, 3\)"),
    (torch.ones(0, 3), None, "K >= 1"),
    (torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]), None, "zero vector"),
    (torch.tensor([[0.0, 0.0, 1.0], [float("nan")] * 3]), None, r"non-finite \(NaN or inf\) components in rows \[1\]"),
    (torch.tensor([[float("inf"), 0.0, 1.0]]), None, r"non-finite \(NaN or inf\) components in rows \[0\]"),
    (torch.ones(1, 3), 1, "n_slabs must be a whole number >= 2"),
])
def test_bad_directions_and_slab_counts_are_named(directions, n_slabs, message):
    with pytest.raises(ValueError, match=message):
        MiddleSlab(GRID, directions, n_slabs)


@pytest.mark.parametrize("grid", [16, (16, 16, 16)])
def test_a_grid_that_is_no_grid_is_named(grid):
    """Before: make_operator(16, dirs) failed with "AttributeError: 'int' object has no attribute 'shape'"."""
    with pytest.raises(TypeError, match=r"grid must be a dipnet.Grid, e.g. Grid\(\d+, ndim=3, extent=100.0\)"):
        make_operator(grid, torch.eye(3))
    with pytest.raises(TypeError, match="grid must be a dipnet.Grid"):
        MiddleSlab(grid, torch.eye(3))


def test_only_the_working_ball_counts_forward_and_back():
    """A full cube: the profile holds the volume of the voxels inside the working ball only, and the adjoint is
    zero outside it; both single and batched calls."""
    op = MiddleSlab(GRID, torch.eye(3, dtype=torch.float64))
    inside = GRID.working_mask()
    full = torch.ones(GRID.shape, dtype=torch.float64)
    prof = op(full)
    assert prof.shape == (3, 8)
    torch.testing.assert_close(prof[:, 4], torch.full((3,), float(inside.sum()) * GRID.voxel_volume,
                                                      dtype=torch.float64))
    assert float(prof[:, [0, 1, 2, 3, 5, 6, 7]].abs().max()) == 0.0
    back = op.adjoint(torch.ones(2, 3, 8, dtype=torch.float64))  # batched
    assert back.shape == (2, *GRID.shape)
    assert float(back[:, ~inside].abs().max()) == 0.0
    torch.testing.assert_close(back[:, inside], torch.full_like(back[:, inside], 3 * GRID.voxel_volume))


@pytest.mark.parametrize("backend", sorted(BACKENDS))
@pytest.mark.parametrize("outside", [float("nan"), float("inf")])
def test_values_outside_the_working_ball_do_not_count_even_when_not_finite(backend, outside):
    """Before: the fourier backend gave every slab NaN for a volume holding NaN or inf outside the working ball
    (masked by multiplying: inf * 0 is NaN), while splat and rotate_sum ignored them as the contract says."""
    grid = Grid(12, ndim=2)
    op = make_operator(grid, torch.tensor([[1.0, 0.0], [0.6, 0.8]], dtype=torch.float64), backend=backend)
    inside = grid.working_mask().double()
    torch.testing.assert_close(op(torch.where(grid.working_mask(), 1.0, outside).double()), op(inside))
    volume = inside.clone().requires_grad_(True)
    op(volume).sum().backward()
    assert float(volume.grad[~grid.working_mask()].abs().max()) == 0.0


def test_cumulative_is_the_submerged_volume():
    op = MiddleSlab(GRID, torch.eye(3, dtype=torch.float64))
    x = torch.rand(2, *GRID.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    cum = op.cumulative(x)
    assert cum.shape == (2, 3, 8)
    torch.testing.assert_close(cum, torch.cumsum(op(x), dim=-1))
    torch.testing.assert_close(cum[..., -1], op(x).sum(-1))  # all slabs under water: the whole volume
    assert bool((cum.diff(dim=-1) >= 0).all())  # a non-negative volume only ever adds


def test_the_scipy_view_is_the_operator_and_its_transpose():
    op = MiddleSlab(GRID, torch.eye(3, dtype=torch.float64), n_slabs=4)
    linear = op.as_linear_operator()
    assert linear.shape == (3 * 4, GRID.n**3) and linear.dtype == np.float64
    rng = np.random.default_rng(0)
    x, y = rng.random(GRID.n**3), rng.random(12)
    with torch.no_grad():
        np.testing.assert_allclose(linear.matvec(x), op(torch.from_numpy(x).reshape(GRID.shape)).reshape(-1).numpy())
        np.testing.assert_allclose(linear.rmatvec(y), op.adjoint(torch.from_numpy(y).reshape(3, 4)).reshape(-1).numpy())
    assert np.dot(linear.matvec(x), y) == pytest.approx(np.dot(x, linear.rmatvec(y)), rel=1e-12)


def test_wrong_shapes_are_named():
    op = MiddleSlab(GRID, torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"volume must have shape \(8, 8, 8\)"):
        op(torch.zeros(8, 8))
    with pytest.raises(ValueError, match=r"profiles must have shape \(K, M\) = \(3, 8\)"):
        op.adjoint(torch.zeros(2, 8))
    with pytest.raises(TypeError, match="abstract"):
        DipOperator(GRID, torch.eye(3))


BACKEND_NAMES = sorted(BACKENDS)


@pytest.mark.parametrize("backend", BACKEND_NAMES)
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_every_backend_names_non_finite_directions(backend, bad):
    directions = torch.tensor([[0.0, 0.0, 1.0], [bad, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"non-finite \(NaN or inf\) components in rows \[1\]"):
        make_operator(GRID, directions, backend=backend)


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_bool_integer_and_numpy_occupancies_are_accepted_as_floats(backend):
    """A binary reconstruction (bool), an integer occupancy and a numpy array give the profiles of the same
    occupancy as float64, in the operator's float dtype; the adjoint takes integer and numpy profiles alike."""
    op = make_operator(GRID, torch.eye(3, dtype=torch.float64), backend=backend)
    occupied = torch.rand(GRID.shape, generator=torch.Generator().manual_seed(1)) > 0.5
    expected = op(occupied.double())
    for volume in (occupied, occupied.int(), occupied.long(), occupied.numpy(), occupied.double().numpy()):
        prof = op(volume)
        assert isinstance(prof, torch.Tensor) and prof.dtype == torch.float64
        torch.testing.assert_close(prof, expected)
    torch.testing.assert_close(op(torch.stack([occupied, occupied])), torch.stack([expected, expected]))
    counts = torch.arange(3 * 8).reshape(3, 8)
    back = op.adjoint(counts.double())
    for profiles in (counts, counts.numpy()):
        torch.testing.assert_close(op.adjoint(profiles), back)
    with pytest.raises(TypeError, match=r"volume must be real .* got dtype torch.complex128"):
        op(occupied.to(torch.complex128))
    with pytest.raises(TypeError, match="profiles must be real"):
        op.adjoint(counts.to(torch.complex64))


def test_numpy_views_with_negative_strides_are_accepted():
    """Before: a flipped numpy volume (np.flip, [::-1]), profiles or directions failed with "ValueError: At least one
    stride in the given numpy array is negative, and tensors with negative strides are not currently supported",
    though the operator takes numpy arrays."""
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], dtype=torch.float64)
    op = make_operator(GRID, dirs.numpy()[::-1])
    torch.testing.assert_close(op.directions, dirs.flip(0))
    volume = np.random.default_rng(0).random(GRID.shape)
    torch.testing.assert_close(op(np.flip(volume, 0)), op(torch.from_numpy(volume.copy()).flip(0)))
    profiles = np.arange(2.0 * GRID.n).reshape(2, GRID.n)
    torch.testing.assert_close(op.adjoint(profiles[:, ::-1]), op.adjoint(torch.from_numpy(profiles).flip(1)))


def test_float16_volumes_and_profiles_are_refused_naming_the_dtype():
    """Before: a float16 volume of a 100 mm cube gave profiles of inf without a word (its slabs of 1.25e5 mm^3
    exceed float16's 65504); bfloat16 is kept (its range holds them)."""
    grid = Grid(16, ndim=3, extent=200.0)
    op = make_operator(grid, torch.eye(3, dtype=torch.float64))
    cube = torch.zeros(grid.shape)
    cube[4:-4, 4:-4, 4:-4] = 1.0  # inside the working ball
    with pytest.raises(TypeError, match=r"volume in float16 cannot hold slab volumes .*65504.*float32"):
        op(cube.half())
    with pytest.raises(TypeError, match=r"profiles in float16"):
        op.adjoint(op(cube).half())
    profiles = op(cube.bfloat16())
    assert profiles.dtype == torch.bfloat16 and torch.isfinite(profiles).all()
    assert float(profiles.float().sum(1).min()) == pytest.approx(float(cube.sum()) * grid.voxel_volume, rel=0.01)


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_float_inputs_keep_their_dtype_and_their_gradient(backend):
    """A float32 volume that requires grad is used as it is: float32 profiles, and the gradient of
    ``<A x, y>`` reaches ``x`` as ``A^T y``."""
    op = make_operator(GRID, torch.eye(3, dtype=torch.float64), backend=backend)
    x = torch.rand(GRID.shape, generator=torch.Generator().manual_seed(2)).requires_grad_()
    y = torch.rand(3, 8, generator=torch.Generator().manual_seed(3))
    prof = op(x)
    assert prof.dtype == torch.float32 and prof.requires_grad
    (prof * y).sum().backward()
    torch.testing.assert_close(x.grad, op.adjoint(y), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_every_backend_casts_as_a_module(backend):
    """``.float()``, ``.double()``, ``.to()``, ``.cpu()`` and a module holding the operator work on every backend
    (the Fourier backend once shadowed ``nn.Module._apply``, which they all call), and a float32 operator gives
    float32 profiles equal to the float64 ones to single precision."""
    op = make_operator(GRID, torch.eye(3, dtype=torch.float64), backend=backend)
    x = torch.rand(GRID.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    expected = op(x)
    assert op.float() is op and op.directions.dtype == torch.float32
    torch.testing.assert_close(op(x.float()), expected.float(), rtol=1e-4, atol=1e-3)
    assert op.double() is op and op.directions.dtype == torch.float64
    assert op.to(torch.float64).cpu() is op
    torch.nn.Sequential(op).to("cpu")
    torch.testing.assert_close(op(x), expected)
