"""The Fourier-slice backend (dipnet.operators.fourier): the exact box-voxel model, input dtypes, single precision,
option checks, pickling."""

from __future__ import annotations

import pickle

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.operators import FourierOperator
from dipnet.operators.fourier import MAX_EPS
from dipnet.operators.box_model import box_voxel_profiles

from operator_problems import generic_directions, random_problem, rel_error


@pytest.mark.parametrize("n,ndim", [(32, 3), (31, 3), (64, 2)])
def test_fourier_matches_exact_box_voxel_model(n, ndim):
    grid = Grid(n, ndim)
    centers = grid.centers()
    cube = ((centers - torch.tensor([5.0, -3.0, 2.0][:ndim])).abs().max(-1).values < 25).to(torch.float64)
    axis = torch.zeros(1, ndim, dtype=torch.float64)
    axis[0, -1] = 1.0  # the hardest orientation: faces aligned with the slabs
    dirs = torch.cat([axis, generic_directions(5, ndim)])
    exact = box_voxel_profiles(grid, dirs, n, cube)
    prof = FourierOperator(grid, dirs)(cube)
    assert rel_error(prof, exact) < 1e-3
    assert ((prof - exact).norm(dim=1) / exact.norm(dim=1)).max() < 2e-3


def test_fourier_float32_input_keeps_dtype():
    grid, dirs, x, _ = random_problem(3, seed=5)
    op = FourierOperator(grid, dirs, 20)
    out = op(x.float())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), op(x), rtol=1e-5, atol=1e-4)


def test_fourier_single_precision_keeps_accuracy_and_adjoint():
    grid, dirs, x, _ = random_problem(3, seed=6)
    double = FourierOperator(grid, dirs, 20, eps=1e-4)
    single = FourierOperator(grid, dirs, 20, eps=1e-4, single=True)
    assert rel_error(single(x), double(x)) < 1e-4  # both within the requested eps (measured 1.6e-5)
    y = torch.rand(single.profile_shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    lhs, rhs = float((single(x) * y).sum()), float((x * single.adjoint(y)).sum())
    assert abs(lhs - rhs) <= 3e-7 * abs(lhs)  # the exact transpose, to single-precision rounding (measured < 7e-8)
    with pytest.raises(ValueError, match="single-precision NUFFT needs eps"):
        FourierOperator(grid, dirs, 20, eps=1e-7, single=True)


@pytest.mark.parametrize("option", [{"bandwidth": 0.5}, {"axis_boost": 0.0}, {"bandwidth": float("nan")},
                                    {"bandwidth": float("inf")}, {"axis_boost": True}])
def test_bandwidths_below_the_slab_nyquist_are_refused(option):
    """Before: an infinite bandwidth ended in numpy's "repeats may not contain negative values", ``True`` ran as 1."""
    grid = Grid(8, 3)
    name = next(iter(option))
    with pytest.raises(ValueError, match=f"{name} must be a finite number >= 1"):
        FourierOperator(grid, generic_directions(2, 3), **option)


@pytest.mark.parametrize("option,message", [
    # NaN: segmentation fault in finufft; <= 1: finufft's "opts.upsampfac not > 1.0" at the first transform
    ({"upsampfac": float("nan")}, r"upsampfac \(the NUFFT's oversampling factor\) must be null"),
    ({"upsampfac": 1.0}, r"upsampfac .* in \[1.15, 3\] \(finufft's range\), got 1.0"),
    ({"upsampfac": 0}, r"upsampfac .*got 0"),  # ran as finufft's choice, unsaid
    ({"nthreads": -1}, r"nthreads .* must be a whole number >= 1, got -1"),  # ran as the default
    ({"nthreads": 2.5}, "nthreads .* must be a whole number, got 2.5"),  # ran 2 threads
    ({"single": "no", "eps": 1e-3}, "single must be true or false, got 'no'"),  # ran in complex64
])
def test_nufft_options_are_checked_before_any_transform(option, message):
    with pytest.raises(ValueError, match=message):
        FourierOperator(Grid(8, 3), generic_directions(2, 3), **option)
    FourierOperator(Grid(8, 3), generic_directions(2, 3), upsampfac=1.25, nthreads=1)  # in range


def test_the_tolerance_is_limited_to_where_the_operator_stays_accurate():
    """Before: ``operator.eps=0.1`` was accepted and ruined the operator silently (profiles 18 % off, their sums
    24 %; a ball's reconstruction IoU 0.70 instead of 0.945, named only by its volume ratio). The largest eps
    accepted keeps a random volume's profiles within 0.5 % of a tight tolerance's."""
    grid, dirs, x, _ = random_problem(3, seed=7)
    tight = FourierOperator(grid, dirs, 20, eps=1e-9)(x)
    assert rel_error(FourierOperator(grid, dirs, 20, eps=MAX_EPS)(x), tight) < 5e-3
    for eps in (0.1, 0.0, -1e-6, float("nan")):
        with pytest.raises(ValueError, match=r"eps \(the NUFFT's relative tolerance\) must lie in \(0, 0.01\]"):
            FourierOperator(grid, dirs, 20, eps=eps)


def test_a_pickled_operator_rebuilds_its_plan_and_gives_the_same_profiles():
    """The NUFFT plan (C memory) is dropped when pickling (as for a worker process) and rebuilt on first use."""
    grid, dirs, x, _ = random_problem(3, seed=10)
    op = FourierOperator(grid, dirs, 20)
    before = op(x)
    assert op._plan is not None
    copy = pickle.loads(pickle.dumps(op))
    assert copy._plan is None
    torch.testing.assert_close(copy(x), before, rtol=1e-12, atol=1e-12)


def test_the_zero_frequency_is_the_volume_and_the_period_leaves_no_wrap_around():
    """Each profile sums to the volume (the n = 0 term), and the period holds the whole support plus the slab
    range: a ball at the working region's top edge is not folded onto the slabs far from it."""
    grid = Grid(32, 3, 100.0)
    dirs = generic_directions(3, 3)
    op = FourierOperator(grid, dirs)
    assert op.period >= grid.radius + (grid.voxel_size * 3**0.5 + op.slab_thickness) / 2 + grid.extent / 2
    r, centre = 10.0, torch.tensor([0.0, 0.0, grid.radius - 10.0], dtype=torch.float64)
    ball = (grid.centers() - centre).norm(dim=-1).le(r).to(torch.float64)
    prof = op(ball)
    volume = float((ball * grid.working_mask()).sum()) * grid.voxel_volume
    torch.testing.assert_close(prof.sum(1), torch.full((3,), volume, dtype=torch.float64), rtol=1e-5, atol=0.0)
    edges = op.slab_edges()
    mids = (edges[1:] + edges[:-1]) / 2
    far = (mids[None, :] - (dirs @ centre)[:, None]).abs() > r + 2 * grid.voxel_size  # (K, M)
    assert int(far.sum()) > 40 and float(prof[far].abs().max()) < 1e-4 * float(prof.max())


def test_threads_do_not_change_the_result():
    grid, dirs, x, _ = random_problem(3, seed=11)
    one, two = FourierOperator(grid, dirs, 20, nthreads=1), FourierOperator(grid, dirs, 20, nthreads=2)
    assert (one.nthreads, two.nthreads) == (1, 2)
    torch.testing.assert_close(two(x), one(x), rtol=1e-10, atol=1e-10)
