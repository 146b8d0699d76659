import pytest
import torch

from dipnet.core.grid import Grid


def test_voxel_centres_follow_the_convention():
    g = Grid(4, 3, 8.0)
    assert g.voxel_size == 2.0 and g.voxel_volume == 8.0 and g.shape == (4, 4, 4)
    c = g.centers()
    assert c.shape == (4, 4, 4, 3)
    # [z, y, x] indexing, (x, y, z) components, centred on the origin
    assert torch.equal(c[0, 0, 3], torch.tensor([3.0, -3.0, -3.0], dtype=torch.float64))
    assert torch.equal(c[2, 1, 0], torch.tensor([-3.0, -1.0, 1.0], dtype=torch.float64))
    assert torch.allclose(c.mean(dim=(0, 1, 2)), torch.zeros(3, dtype=torch.float64))


def test_working_mask_is_the_inscribed_ball_less_one_voxel():
    g = Grid(32, 3, 64.0)
    mask = g.working_mask()
    r = g.centers().norm(dim=-1)
    assert bool((r[mask] <= g.radius).all()) and bool((r[~mask] > g.radius).all())
    assert g.radius == 30.0
    # the mask fills about the ball's share of the cube
    assert abs(mask.float().mean().item() - (4 / 3) * torch.pi * (30 / 64) ** 3) < 0.01


def test_2d_grid():
    g = Grid(10, 2, 5.0)
    assert g.shape == (10, 10) and g.centers().shape == (10, 10, 2) and g.voxel_volume == 0.25


def test_a_whole_float_resolution_is_stored_as_an_int():
    """``Grid(15.0)`` (a resolution read from a file or computed) is the grid ``Grid(15)``: operators and shapes
    index with ``n``, and failed with a raw TypeError on the float."""
    import numpy as np

    from dipnet.operators import make_operator
    from dipnet.core.orientations import fibonacci_hemisphere

    for n in (15.0, np.int64(15)):
        g = Grid(n, 3, 90)
        assert g == Grid(15, 3, 90.0) and type(g.n) is int and type(g.extent) is float
        assert make_operator(g, fibonacci_hemisphere(4))(torch.ones(g.shape)).shape == (4, 15)


@pytest.mark.parametrize("kwargs", [dict(n=0), dict(n=3), dict(n=8.5), dict(n=8, ndim=4), dict(n=8, extent=0.0),
                                    dict(n=8, extent=-1.0), dict(n=True), dict(n=8, ndim=True)])
def test_bad_grids_are_refused(kwargs):
    with pytest.raises(ValueError):
        Grid(**kwargs)


@pytest.mark.parametrize("extent,message", [(float("inf"), "finite, positive number"), (1e-300, "voxels of 0 mm\\^3"),
                                            (1e300, "voxels of inf mm\\^3")])
def test_an_extent_whose_voxels_float64_cannot_hold_is_refused(extent, message):
    """Before: Grid(16, extent=inf) and extent=1e300 were accepted and every operator failed with
    'ZeroDivisionError: integer division or modulo by zero'; extent=1e-300 gave profiles of 0 mm^3, no word."""
    with pytest.raises(ValueError, match=message):
        Grid(16, 3, extent)
    assert Grid(16, 3, 1e-3).voxel_volume == pytest.approx((1e-3 / 16) ** 3)
