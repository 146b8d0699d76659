"""The moment test of a declared symmetry: the group's closure, an analytic misfit (a ball off a mirror plane),
symmetric and asymmetric 2D shapes, whole dips only, and too few dips."""

import math

import numpy as np
import pytest
from analytic_profiles import ball_measurement

from dipnet.core.grid import Grid
from dipnet.core.orientations import angles_2d, directions_2d, fibonacci_hemisphere
from dipnet.preprocessing.symmetry_moments import MISFIT_LIMIT, group_closure, symmetry_fit, whole_dips
from dipnet.shapes import builtin_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.priors import symmetry_maps


def _group(ndim, **spec):
    return group_closure([m.numpy() for m in symmetry_maps(ndim, **spec)])


def test_the_closure_of_generators_is_the_whole_group_identity_first():
    assert len(_group(3, plane_normal=[1, 0, 0], axis=[0, 0, 1], order=4)) == 8  # D4
    assert len(_group(3, axis=[0, 0, 1], order=3)) == 3 and len(_group(2, order=6)) == 6
    assert np.allclose(_group(2, plane_normal=[0, 1])[0], np.eye(2))
    irrational = np.array([[math.cos(1.0), -math.sin(1.0)], [math.sin(1.0), math.cos(1.0)]])
    with pytest.raises(ValueError, match="more than"):
        group_closure([irrational])


def test_a_ball_off_a_mirror_plane_misfits_as_the_centroid_says():
    """Order 1: the mirror across x forces ``c_x = 0``, so the invariant fit misses ``x0 theta_x`` less its mean:
    misfit ``x0 std(theta_x) / r_g`` with ``r_g^2 = r^2 / 5 + h^2 / 12`` (a ball's second moment and the slabs').
    Order 3 (``3 (c . theta) r_g^2`` over ``3 r_g^3``) says the same, up to terms in ``(x0 / r_g)^3``."""
    directions = fibonacci_hemisphere(41).numpy()
    x0, radius, h = 0.5, 20.0, 1.0
    fit = symmetry_fit(ball_measurement([x0, 0.0, 0.0], radius, directions, h), _group(3, plane_normal=[1, 0, 0]))
    expected = x0 * directions[:, 0].std() / math.sqrt(radius**2 / 5 + h**2 / 12)
    assert fit.order in (1, 3) and fit.misfit == pytest.approx(expected, rel=2e-3) and fit.rejected
    for spec in ({"plane_normal": [0, 1, 0]}, {"axis": [1, 0, 0], "order": 4}):  # symmetries it has
        kept = symmetry_fit(ball_measurement([x0, 0.0, 0.0], radius, directions, h), _group(3, **spec))
        assert not kept.rejected and kept.misfit < 1e-4, (spec, kept)


@pytest.mark.parametrize("snr_db", [None, 25.0])
def test_the_elephants_mirrors_are_rejected_and_the_disks_are_not(snr_db):
    grid = Grid(32, 2, 100.0)
    directions = directions_2d(angles_2d(12))
    sensor = LevelSensor(snr_db=snr_db, seed=4) if snr_db else None
    for name, has in (("elephant", False), ("disk", True)):
        measurement = simulate_measurement(builtin_shape(name, 2, 45.0), directions, grid=grid, sensor=sensor,
                                           seed=4, progress=False)[1]
        for spec in ({"plane_normal": [1, 0]}, {"plane_normal": [0, 1]}):
            fit = symmetry_fit(measurement, _group(2, **spec))
            assert fit.rejected is not has and fit.dips == 12, (name, spec, fit)
            assert (fit.misfit > 3 * MISFIT_LIMIT) if not has else (fit.misfit < MISFIT_LIMIT), (name, spec, fit)


def test_only_whole_dips_count():
    directions = fibonacci_hemisphere(20).numpy()
    measurement = ball_measurement([0.0, 0.0, 0.0], 20.0, directions)
    measurement.metadata.update(recorded={"truncated": [0, 3], "truncated_policy": "keep"},
                                interpolated_orientations=5)
    assert list(whole_dips(measurement)) == [1, 2] + list(range(4, 15))
    measurement.metadata["recorded"]["truncated_policy"] = "drop"  # the listed dips are gone already
    assert len(whole_dips(measurement)) == 15


def test_too_few_dips_leave_an_order_untested_and_nothing_rejected():
    """3D order 3 has 10 coefficients and a constant: 12 dips leave 1 degree of freedom, so orders 1 and 2 alone
    are tested; 4 dips test nothing."""
    off = ball_measurement([4.0, 0.0, 0.0], 20.0, fibonacci_hemisphere(12).numpy())
    fit = symmetry_fit(off, _group(3, plane_normal=[1, 0, 0]))
    assert fit.order in (1, 2) and fit.rejected
    none = symmetry_fit(ball_measurement([4.0, 0.0, 0.0], 20.0, fibonacci_hemisphere(4).numpy()),
                        _group(3, plane_normal=[1, 0, 0]))
    assert none.order == 0 and math.isnan(none.misfit) and not none.rejected and none.dips == 4
