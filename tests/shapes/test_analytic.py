"""Analytic and built-in shapes: consistent dips and occupancy, the water-filled chamber."""

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.shapes import (DEFAULT_SHAPE, Ball, Box, ChamberBox, ShapeError, Torus, builtin_names, builtin_shape,
                           from_trimesh)

ALL_BUILTINS = [(3, n) for n in builtin_names(3)] + [(2, n) for n in builtin_names(2)]


def unit_directions(k: int, d: int, seed: int) -> torch.Tensor:
    v = torch.randn(k, d, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return v / v.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("ndim,name", ALL_BUILTINS)
def test_builtin_dips_are_consistent(ndim, name):
    """volume_below: 0 below the shape, = volume at the top, non-decreasing in h."""
    radius = 40.0
    shape = builtin_shape(name, ndim, radius)
    assert shape.ndim == ndim and shape.radius() == pytest.approx(radius)
    h = torch.linspace(-1.05 * radius, 1.05 * radius, 101)
    v = shape.volume_below(unit_directions(12, ndim, 0), h)
    assert v.shape == (12, 101)
    torch.testing.assert_close(v[:, 0], torch.zeros(12, dtype=torch.float64))
    torch.testing.assert_close(v[:, -1], torch.full((12,), shape.volume, dtype=torch.float64))
    assert (v.diff(dim=1) >= -1e-9 * shape.volume).all()


@pytest.mark.parametrize("ndim,name", ALL_BUILTINS)
def test_builtin_occupancy_matches_volume(ndim, name):
    grid = Grid(40 if ndim == 3 else 96, ndim, 100.0)
    shape = builtin_shape(name, ndim, 0.9 * grid.radius)
    occ = shape.occupancy(grid, supersample=2)
    assert occ.shape == grid.shape and occ.dtype == torch.float32
    assert 0 <= occ.min() and occ.max() <= 1
    assert occ.sum().item() * grid.voxel_volume == pytest.approx(shape.volume, rel=0.05)
    assert not occ[~grid.working_mask()].any()  # fits in the working region


def test_supersampling_improves_partial_volume():
    grid = Grid(24, 3, 100.0)
    shape = builtin_shape("ball", 3, 0.9 * grid.radius)
    err = [abs(shape.occupancy(grid, s).sum().item() * grid.voxel_volume / shape.volume - 1)
           for s in (1, 4)]
    assert err[1] < err[0] and err[1] < 3e-3


def test_default_is_the_chamber_box():
    assert DEFAULT_SHAPE == "chamber_box"
    assert all(DEFAULT_SHAPE in builtin_names(d) for d in (2, 3))


@pytest.mark.parametrize("ndim", [2, 3])
def test_chamber_is_empty_and_counted_as_water(ndim):
    a = 30.0
    shape = ChamberBox([a] * ndim, chamber_half_sizes=12.0, channel_half_width=4.0)
    lo, hi = shape.chamber
    chamber_vol = np.prod(hi - lo)
    channel_vol = 8.0 ** (ndim - 1) * (a - 12.0)
    assert shape.volume == pytest.approx((2 * a) ** ndim - chamber_vol - channel_vol)
    grid = Grid(32 if ndim == 3 else 64, ndim, 100.0)
    occ = shape.occupancy(grid, supersample=2)
    centres = grid.centers().numpy()
    in_chamber = np.all(np.abs(centres) < 12.0 - grid.voxel_size, axis=-1)
    in_wall = np.all(np.abs(centres) < a - grid.voxel_size, axis=-1) & ~np.all(
        np.abs(centres) < 12.0 + grid.voxel_size, axis=-1
    )
    in_wall &= np.abs(centres[..., 0]) > 4.0 + grid.voxel_size  # away from the channel
    assert in_chamber.any() and (occ[torch.from_numpy(in_chamber)] == 0).all()
    assert (occ[torch.from_numpy(in_wall)] == 1).all()
    # water fills the chamber: the displaced volume excludes it
    up = torch.zeros(1, ndim, dtype=torch.float64)
    up[0, -1] = 1.0
    v = shape.volume_below(up, torch.tensor([-a, 0.0, a]))[0]
    below_half = (2 * a) ** (ndim - 1) * a - chamber_vol / 2
    expect = torch.tensor([0.0, below_half, shape.volume], dtype=torch.float64)
    torch.testing.assert_close(v, expect)


def _box_mesh(lo, hi):
    m = trimesh.creation.box(extents=np.subtract(hi, lo))
    m.apply_translation(np.add(lo, hi) / 2)
    return m


def test_chamber_box_equals_boolean_mesh_and_is_not_a_sealed_void():
    """The box algebra matches a boolean mesh (manifold3d); the loader sees the chamber as open,
    and fills it once the channel is removed (then it is a sealed void)."""
    a, c, w = 30.0, 12.0, 4.0
    shape = ChamberBox([a] * 3, chamber_half_sizes=c, channel_half_width=w)
    outer = _box_mesh([-a] * 3, [a] * 3)
    chamber = _box_mesh([-c] * 3, [c] * 3)
    channel = _box_mesh([-w, -w, 0.0], [w, w, a + 5])  # overlaps: avoids coplanar faces
    open_mesh = outer.difference(chamber.union(channel))
    mesh_shape = from_trimesh(open_mesh, center=False)
    assert mesh_shape.notes == [] and mesh_shape.volume == pytest.approx(shape.volume, rel=1e-9)
    d = unit_directions(10, 3, 5)
    h = torch.linspace(-55, 55, 57)
    torch.testing.assert_close(
        mesh_shape.volume_below(d, h), shape.volume_below(d, h), rtol=1e-9, atol=1e-6
    )
    with pytest.warns(UserWarning, match="sealed"):
        sealed = from_trimesh(trimesh.util.concatenate([outer, chamber]), center=False)
    assert sealed.volume == pytest.approx((2 * a) ** 3)


def test_torus_volume_and_dips():
    torus = Torus(20.0, 8.0)
    assert torus.volume == pytest.approx(2 * np.pi**2 * 20.0 * 8.0**2, rel=3e-3)
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    v = torus.volume_below(up, torch.tensor([0.0]))
    assert v.item() == pytest.approx(torus.volume / 2, rel=1e-9)  # symmetric about z = 0


@pytest.mark.parametrize(
    "args",
    [("nope", 3, 10.0), ("elephant", 3, 10.0), ("ball", 3, -1.0), ("ball", 4, 10.0)],
)
def test_builtin_errors(args):
    with pytest.raises(ShapeError):
        builtin_shape(*args)


def test_bad_chamber_geometry():
    with pytest.raises(ShapeError, match="inside"):
        ChamberBox([10.0] * 3, chamber_half_sizes=10.0, channel_half_width=1.0)
    with pytest.raises(ShapeError, match="narrower"):
        ChamberBox([10.0] * 3, chamber_half_sizes=5.0, channel_half_width=6.0)


@pytest.mark.parametrize("radius", [float("inf"), 1e300, 1e-300, float("nan"), 0.0, -1.0])
def test_ball_radius_must_be_finite_and_positive(radius):
    with pytest.raises(ShapeError, match=r"ball radius must be a finite, positive number of mm in \[1e-12, 1e\+12\]"):
        Ball(radius)


def test_a_centre_or_size_that_is_not_finite_is_refused():
    """The audit's case: ``Ball(30, center=(nan, 0, 0))`` was made, and failed later as "grid extent must be
    positive (mm), got nan"."""
    with pytest.raises(ShapeError, match=r"center must be finite numbers \(mm\), got \[nan, 0.0, 0.0\]"):
        Ball(30.0, center=(float("nan"), 0.0, 0.0))
    with pytest.raises(ShapeError, match="half_sizes must be finite"):
        ChamberBox((10.0, float("inf"), 10.0), chamber_half_sizes=5.0, channel_half_width=2.0)


def test_occupancy_on_a_resolution_instead_of_a_grid_is_named():
    """Before: shape.occupancy(16) failed with "AttributeError: 'int' object has no attribute 'ndim'"."""
    for shape in (Ball(10.0), ChamberBox([10.0] * 3, chamber_half_sizes=5.0, channel_half_width=1.0)):
        with pytest.raises(TypeError, match=r"grid must be a dipnet.Grid, e.g. Grid\(16, "):
            shape.occupancy(16)


@pytest.mark.parametrize("bad", [0, -1, 1.5, float("nan")])
def test_every_shape_refuses_a_supersample_below_one_even_the_exact_boxes(bad):
    """The boxes answer exactly, without sampling, and took ``supersample=0`` or ``-1`` without a word; every shape
    refuses it with the one message of :func:`dipnet.shapes.base.check_supersample`."""
    grid = Grid(8, 3, 100.0)
    for shape in (Box((20.0, 20.0, 20.0)), builtin_shape("chamber_box", ndim=3, radius=30.0), Ball(20.0),
                  Torus(25.0, 8.0)):
        with pytest.raises(ValueError, match="supersample must be a positive integer"):
            shape.occupancy(grid, supersample=bad)
    assert Box((20.0, 20.0, 20.0)).occupancy(grid, supersample=2.0).shape == grid.shape  # a whole float is fine
