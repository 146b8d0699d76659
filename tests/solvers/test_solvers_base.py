"""The solver interface (dipnet.solvers.base): a solver is abstract until it solves; the measured profiles are put
on the operator's slabs (as they are, or resampled keeping every slab's volume) or refused when they are not
the operator's dips."""

from __future__ import annotations

import warnings

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.solvers import make_solver
from dipnet.solvers.base import Solver, measured_profiles, measured_sigma, on_operator_slabs


def _measurement(k=4, m=10):
    """k random profiles of m slabs 2.5 mm thick from -12.5 mm, along Fibonacci directions."""
    gen = torch.Generator().manual_seed(0)
    profiles = torch.rand(k, m, generator=gen, dtype=torch.float64)
    return DipMeasurement(directions=fibonacci_hemisphere(k), profiles=profiles, slab_thickness=2.5,
                          offsets=torch.full((k,), -12.5))


def test_measured_profiles_aligns_to_the_operator():
    grid = Grid(16, 3, 40.0)
    op = make_operator(grid, fibonacci_hemisphere(4), 10)
    m = _measurement()
    m.slab_thickness, m.offsets = op.slab_thickness, torch.full((4,), -20.0)
    assert torch.equal(measured_profiles(m, op), m.profiles)
    with pytest.raises(ValueError, match="orientations"):
        measured_profiles(m, make_operator(grid, fibonacci_hemisphere(5), 10))


def test_profiles_on_other_slabs_are_resampled_keeping_the_volume():
    """The measurement's 10 slabs of 2.5 mm from -12.5 mm, the operator's 16 slabs of 2.5 mm from -20 mm: the
    profiles land shifted by 3 slabs, zero outside, each slab's volume unchanged."""
    grid = Grid(16, 3, 40.0)
    op = make_operator(grid, fibonacci_hemisphere(4))
    m = _measurement()
    on_op = measured_profiles(m, op)
    assert on_op.shape == (4, 16) and on_op.dtype == torch.float64
    torch.testing.assert_close(on_op[:, 3:13], m.profiles)
    assert float(on_op[:, :3].abs().max()) == 0.0 and float(on_op[:, 13:].abs().max()) == 0.0
    on_op[0, 5] = -1.0
    assert float(m.profiles[0, 2]) != -1.0  # a copy: the measurement is not changed through it


def test_resampling_onto_narrower_slabs_warns_of_the_volume_it_drops():
    """The measurement's slabs [-12.5, 12.5] mm onto an operator's [-10, 10] mm: the outer slab at each end (about
    a fifth of a random profile) is dropped, which is warned about naming both slab ranges; onto [-20, 20] mm
    nothing is dropped and nothing said."""
    m = _measurement()
    with pytest.warns(UserWarning, match=r"from slabs \[-12\.5, 12\.5\] mm onto \[-10\.0, 10\.0\] mm drops up to .*"
                                         r"the object does not fit the grid \(raise extent_mm\)"):
        measured_profiles(m, make_operator(Grid(8, 3, 20.0), fibonacci_hemisphere(4)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        measured_profiles(m, make_operator(Grid(16, 3, 40.0), fibonacci_hemisphere(4)))


def test_on_operator_slabs_resamples_once_and_the_sigma_with_the_profiles():
    """The sigma was for the other slabs: it is resampled as ``rebinned`` does for a job reading the ``.npz`` (before,
    it was dropped, and a solve from Python took its noise from the profiles while the job used the stated one)."""
    m = _measurement()
    m.sigma = torch.full_like(m.profiles, 0.1)
    op = make_operator(Grid(16, 3, 40.0), fibonacci_hemisphere(4))
    on_op = on_operator_slabs(m, op)
    torch.testing.assert_close(on_op.profiles, measured_profiles(m, op))
    assert on_op.slab_thickness == op.slab_thickness
    torch.testing.assert_close(on_op.sigma, m.rebinned(op.slab_edges()).sigma)
    assert torch.equal(measured_sigma(m, op), on_op.sigma) and measured_sigma(on_op, op) is on_op.sigma
    torch.testing.assert_close(on_op.offsets, torch.full((4,), -20.0, dtype=on_op.offsets.dtype))
    assert on_operator_slabs(on_op, op) is on_op  # already there: itself
    assert torch.equal(measured_profiles(on_op, op), on_op.profiles)


@pytest.mark.parametrize("name", ["voxel", "implicit", "dip"])
def test_a_solve_on_narrower_slabs_warns_once(name):
    """The voxel solver reads the profiles at each coarse-to-fine stage and round, the others more than once too:
    the volume dropped beyond the operator's slabs is still warned about once per solve."""
    m = _measurement()
    op = make_operator(Grid(16, 3, 20.0), fibonacci_hemisphere(4))  # 16^3: a coarse stage at 8^3 first
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        make_solver(name, iterations=20).solve(m, op)
    assert sum("drops up to" in str(w.message) for w in caught) == 1


def test_other_dimensions_and_other_directions_are_refused():
    m = _measurement()
    with pytest.raises(ValueError, match="measurement has 4 orientations in 3D, the operator 4 in 2D"):
        measured_profiles(m, make_operator(Grid(16, 2, 40.0), torch.eye(2)[[0, 1, 0, 1]] * 1.0))
    with pytest.raises(ValueError, match="the measurement's orientations differ from the operator's"):
        measured_profiles(m, make_operator(Grid(16, 3, 40.0), fibonacci_hemisphere(4).flip(0)))
    # the rows that differ and how to build the operator that fits (before: only the first sentence)
    with pytest.raises(ValueError, match=r"differ from the operator's in 4 of 4 rows \(first: row 0, 180 deg apart; .*"
                                         r"make_operator\(grid, measurement.directions\)"):
        measured_profiles(m, make_operator(Grid(16, 3, 40.0), -fibonacci_hemisphere(4)))


def test_a_solver_must_solve():
    with pytest.raises(TypeError, match="abstract"):
        Solver()

    class Empty(Solver):
        name = "empty"

        def solve(self, measurement, operator):
            return operator.adjoint(measured_profiles(measurement, operator))

    grid = Grid(8, 3, 20.0)
    op = make_operator(grid, fibonacci_hemisphere(4), 8)
    m = _measurement(m=8)
    m.slab_thickness, m.offsets = op.slab_thickness, torch.full((4,), -10.0)
    assert Empty().solve(m, op).shape == grid.shape and Empty.name == "empty" and Solver.name == "solver"


@pytest.mark.parametrize("name,rule,other", [("minnorm", "otsu", "volume"), ("voxel", "volume", "otsu")])
def test_another_solvers_threshold_rule_is_named_as_such(name, rule, other):
    """Before: ``solver.threshold=volume`` with minnorm was refused as "a level of 1 or above leaves an occupancy
    in [0, 1] empty", a reason that does not apply to a rule."""
    with pytest.raises(ValueError, match=rf"got '{other}': this solver's only named rule is '{rule}'") as caught:
        make_solver(name, threshold=other)
    assert "empty" not in str(caught.value)


@pytest.mark.parametrize("name,rule", [("minnorm", "otsu"), ("lsmr", "otsu"), ("voxel", "volume"),
                                       ("implicit", "volume")])
@pytest.mark.parametrize("level", [2.0, 1.0, 0.0, -0.5, float("nan"), True, "0.5"])
def test_a_threshold_outside_the_occupancy_levels_is_refused(name, rule, level):
    """Before: make_solver(name, threshold=2.0) (or nan) gave an empty shape and -0.5 the whole 16^3 grid (4096
    voxels, beyond the working ball's 1472) with no word; only a config's solver.threshold was checked."""
    with pytest.raises(ValueError, match=rf"threshold must be an occupancy level in \(0, 1\) or '{rule}', got"):
        make_solver(name, threshold=level)
    assert make_solver(name, threshold=0.3).threshold == 0.3
    assert make_solver(name, threshold=rule).threshold == rule


@pytest.mark.parametrize("name", ["minnorm", "voxel"])
def test_arguments_that_are_no_measurement_and_operator_are_named(name):
    """Before: solve(operator, measurement) failed with "AttributeError: 'SplatOperator' object has no attribute
    'ndim'", and solve(profiles, operator) (the README's op(occupancy)) with "'Tensor' object has no attribute
    'n_orientations'", in every solver; the message's recipe for profiles makes a measurement that solves."""
    grid = Grid(16, 2)
    op = make_operator(grid, torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.0, 1.0], [-0.6, 0.8]], dtype=torch.float64))
    occupancy = (grid.centers().norm(dim=-1) < 20.0).double()
    profiles = op(occupancy)
    m = DipMeasurement(op.directions, profiles, op.slab_thickness, op.slab_edges()[:1].expand(op.n_orientations))
    solver = make_solver(name, progress=False)
    with pytest.raises(TypeError,
                       match="takes a DipMeasurement and a DipOperator, got SplatOperator and DipMeasurement$"):
        solver.solve(op, m)
    with pytest.raises(TypeError, match=r"got Tensor and SplatOperator; profiles on the operator's slabs make one"):
        solver.solve(profiles, op)
    assert torch.equal(measured_profiles(m, op), profiles)


@pytest.mark.parametrize("value", ["no", "false", "maybe", 2, 0.5, None])
def test_a_solver_flag_that_is_not_true_or_false_is_refused(value):
    """``coarse_to_fine: no`` was read as on (``bool("no")``); the voxel solver refuses it."""
    with pytest.raises(ValueError, match="coarse_to_fine must be true or false"):
        make_solver("voxel", coarse_to_fine=value)
    with pytest.raises(ValueError, match="fit_gain must be true or false"):
        make_solver("voxel", fit_gain=value)
    for name in ("voxel", "implicit", "dip", "minnorm"):  # solver.progress=no drew the progress bars
        with pytest.raises(ValueError, match="progress must be true or false"):
            make_solver(name, progress=value)


def test_a_misspelt_option_or_another_solvers_is_named_with_the_fix():
    """Before: "MinNormSolver.__init__() got an unexpected keyword argument 'tikonov'", naming neither the option meant
    nor the solver that takes it."""
    with pytest.raises(TypeError, match=r"the minnorm solver takes no option\(s\) tikonov \(did you mean tikhonov\?\); "
                                        r"its options: atol, "):
        make_solver("minnorm", tikonov=0.1)
    with pytest.raises(TypeError, match=r"iterations \(an option of voxel, implicit, dip\)"):
        make_solver("minnorm", iterations=10)
