"""Priors: values on hand-computed volumes, autograd against finite differences, config parsing."""

from __future__ import annotations

import math

import pytest
import torch

from dipnet.solvers.fields import OccupancyField
from dipnet.solvers.priors import (BinaryPrior, GradientPenalty, L1Prior, SymmetryPrior, TotalVariation,
                                   TransformL1Prior, VolumePrior, build_priors, dct_matrix, haar_matrix)


def ramp(n: int, ndim: int, power: int = 1) -> torch.Tensor:
    """``o = x^power`` with ``x = i / n`` along the last axis (the grid's x), ``(n,)*ndim`` float64."""
    x = (torch.arange(n, dtype=torch.float64) / n) ** power
    return x.expand((n,) * ndim).clone()


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("isotropic", [True, False])
def test_tv_of_constant_is_zero_and_of_step_is_jump_times_area(ndim, isotropic):
    n, jump = 8, 0.7
    tv = TotalVariation(isotropic=isotropic, eps=1e-9)
    assert float(tv(torch.full((n,) * ndim, 0.3, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-12)
    step = torch.zeros((n,) * ndim, dtype=torch.float64)
    step[..., n // 2:] = jump  # a plane across the whole cube: area 1 in cube units
    assert float(tv(step)) == pytest.approx(jump, rel=1e-6)
    if not isotropic:  # a centred cube of half the side: 2d faces of area (1/2)^(d-1)
        cube = _box(n, ndim, [n // 4] * ndim, [3 * n // 4] * ndim) * jump
        assert float(tv(cube)) == pytest.approx(jump * 2 * ndim * 0.5 ** (ndim - 1), rel=1e-6)


def test_isotropic_tv_is_smaller_than_anisotropic_on_a_diagonal_edge():
    n = 32
    i = torch.arange(n, dtype=torch.float64)
    diag = ((i[:, None] + i[None, :]) >= n).to(torch.float64)  # edge at 45 degrees, length sqrt(2)
    iso, aniso = TotalVariation(True, eps=1e-9)(diag), TotalVariation(False)(diag)
    assert float(aniso) == pytest.approx(2.0, rel=0.05)  # |dx| + |dy| counts the staircase
    assert float(iso) < float(aniso) and float(iso) == pytest.approx(2.0 / 2**0.5, rel=0.1)


@pytest.mark.parametrize("ndim", [2, 3])
def test_gradient_and_laplacian_penalties_on_polynomials(ndim):
    n = 10
    # int |grad x|^2 = 1 over the unit cube; forward differences see n - 1 steps of 1/n per row.
    assert float(GradientPenalty(1)(ramp(n, ndim))) == pytest.approx((n - 1) / n)
    assert float(GradientPenalty(2)(ramp(n, ndim))) == pytest.approx(0.0, abs=1e-18)
    # lap x^2 = 2 everywhere: int 4 over the (n-2)^d interior voxels of volume n^-d.
    assert float(GradientPenalty(2)(ramp(n, ndim, power=2))) == pytest.approx(4 * ((n - 2) / n) ** ndim)
    assert float(GradientPenalty(1)(torch.ones((n,) * ndim))) == 0.0


def _box(n: int, ndim: int, lo, hi) -> torch.Tensor:
    vol = torch.zeros((n,) * ndim, dtype=torch.float64)
    vol[tuple(slice(a, b) for a, b in zip(lo, hi))] = 1.0
    return vol


@pytest.mark.parametrize("ndim", [2, 3])
def test_symmetry_penalty_zero_for_symmetric_and_positive_otherwise(ndim):
    n = 16
    sym = _box(n, ndim, [5] * ndim, [11] * ndim)  # centred cube: mirror and 4-fold symmetric
    off = _box(n, ndim, [5] * ndim, [11] * (ndim - 1) + [14])  # stretched along x (last axis)
    normal_x = [1.0] + [0.0] * (ndim - 1)
    axis = None if ndim == 2 else [0.0, 0.0, 1.0]
    for prior in (SymmetryPrior(plane_normal=normal_x), SymmetryPrior(axis=axis, order=4),
                  SymmetryPrior(plane_normal=normal_x, axis=axis, order=2)):
        assert float(prior(sym)) == pytest.approx(0.0, abs=1e-12)
        assert float(prior(off)) > 0.01
    # Mirroring about y keeps the x-stretched box; a 4-fold rotation does not.
    normal_y = [0.0, 1.0] + [0.0] * (ndim - 2)
    assert float(SymmetryPrior(plane_normal=normal_y)(off)) == pytest.approx(0.0, abs=1e-12)


def test_symmetry_prior_needs_a_symmetry():
    with pytest.raises(ValueError, match="plane_normal"):
        SymmetryPrior()
    with pytest.raises(ValueError, match="axis"):
        SymmetryPrior(order=3)(torch.zeros(4, 4, 4))
    with pytest.raises(ValueError, match="plane_normal must be a non-zero, finite 3-vector"):
        SymmetryPrior(plane_normal=[1.0, 0.0, math.nan])(torch.zeros(4, 4, 4))  # was: "a group of more than 240"
    with pytest.raises(ValueError, match="axis must be a non-zero, finite 3-vector"):
        SymmetryPrior(axis=[0.0, math.inf, 1.0], order=2)(torch.zeros(4, 4, 4))


@pytest.mark.parametrize("order", [2.5, True, float("nan"), 0, "3"])
def test_a_rotation_order_that_is_no_whole_number_is_refused(order):
    """``order: 2.5`` was read as a 2-fold rotation (int), ``true`` as none; the prior and the implicit field's
    built-in symmetry refuse them, naming the value."""
    with pytest.raises(ValueError, match="rotation order must be a whole number >= 1"):
        SymmetryPrior(axis=[0.0, 0.0, 1.0], order=order)
    with pytest.raises(ValueError, match="rotation order must be a whole number >= 1"):
        OccupancyField(3, {"type": "fourier", "n_features": 4, "scale": 1.0}, 4, 1,
                       {"axis": [0.0, 0.0, 1.0], "order": order})


def test_a_whole_float_rotation_order_is_that_order():
    box = _box(16, 3, [5, 5, 5], [14, 11, 11])  # stretched along z (the first axis): 4-fold about z
    assert float(SymmetryPrior(axis=[0.0, 0.0, 1.0], order=4.0)(box)) == pytest.approx(0.0, abs=1e-12)


def test_l1_binary_and_volume_values():
    vol = torch.zeros(4, 4, 4)
    vol[:2] = 1.0  # half full
    assert float(L1Prior()(vol)) == pytest.approx(0.5)
    assert float(L1Prior()(-vol)) == pytest.approx(0.5)
    assert float(BinaryPrior()(vol)) == 0.0
    assert float(BinaryPrior()(torch.full((4, 4), 0.5))) == pytest.approx(0.25)
    assert float(VolumePrior(0.5)(vol)) == pytest.approx(0.0)
    assert float(VolumePrior(0.25)(vol)) == pytest.approx(1.0)  # twice the measured volume


@pytest.mark.parametrize("make", [dct_matrix, haar_matrix])
def test_transforms_are_orthonormal_and_ignore_the_mean(make):
    n = 8
    mat = make(n)
    torch.testing.assert_close(mat @ mat.T, torch.eye(n, dtype=torch.float64))
    prior = TransformL1Prior("dct" if make is dct_matrix else "haar")
    assert float(prior(torch.full((n, n, n), 0.6, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-12)
    # One basis function (2, 1, 3) of unit norm has one coefficient equal to 1.
    basis = torch.einsum("i,j,k->ijk", mat[2], mat[1], mat[3])
    assert float(prior(basis)) == pytest.approx(1.0 / n**3)
    coef = prior.coefficients(basis)
    assert float(coef[2, 1, 3]) == pytest.approx(1.0)


@pytest.mark.parametrize("prior", [
    TotalVariation(isotropic=True), TotalVariation(isotropic=False), GradientPenalty(1), GradientPenalty(2),
    SymmetryPrior(plane_normal=[1.0, 1.0, 0.0]), SymmetryPrior(axis=[0.0, 1.0, 1.0], order=3), L1Prior(),
    TransformL1Prior("dct"), TransformL1Prior("haar"), BinaryPrior(), VolumePrior(0.3),
], ids=lambda p: type(p).__name__)
def test_autograd_matches_finite_differences(prior):
    gen = torch.Generator().manual_seed(0)
    vol = (torch.rand(4, 4, 4, generator=gen, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(prior, (vol,), eps=1e-6, atol=1e-6)


def test_build_priors_from_config():
    built = build_priors({"tv": {"weight": 0.1, "isotropic": False}, "binary": 0.0, "l1": 2,
                          "volume": {"weight": 1.0}}, volume_fraction=0.2)
    assert [(name, weight) for name, weight, _ in built] == [("tv", 0.1), ("l1", 2.0), ("volume", 1.0)]
    assert built[0][2].isotropic is False and built[2][2].fraction == 0.2
    with pytest.raises(ValueError, match="unknown prior"):
        build_priors({"smooth": 1.0})
    with pytest.raises(ValueError, match="bad options"):
        build_priors({"tv": {"weight": 1.0, "isotropc": True}})
    with pytest.raises(ValueError, match="volume fraction"):
        build_priors({"volume": 1.0})
    with pytest.raises(ValueError, match="negative"):
        build_priors({"tv": -1.0})
    # solver.priors.tv.weight=nan (or inf): before, "voxel 8^3: the loss became nan at step 1 of 120 (learning
    # rate 0.1): the optimisation diverged; try a lower solver.lr", blaming the learning rate
    for weight in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"prior 'tv' has weight (nan|inf): a weight is a finite number >= 0"):
            build_priors({"tv": {"weight": weight}})


@pytest.mark.parametrize("isotropic", ["no", "false", 2])
def test_tv_isotropic_given_as_another_word_is_refused(isotropic):
    """``solver.priors.tv.isotropic=no`` was ``bool("no")``, true: the isotropic TV ran where the anisotropic was
    asked for, without a word."""
    with pytest.raises(ValueError, match=r"solver.priors.tv.isotropic\) must be true or false"):
        TotalVariation(isotropic=isotropic)
    assert TotalVariation(isotropic=False).isotropic is False


@pytest.mark.parametrize("spec, match", [
    ({"tv": {"weight": 0.0, "isotropc": True}}, r"bad options for prior 'tv'.*isotropc"),
    ({"tv": {"weight": 0, "isotropic": "no"}}, r"solver.priors.tv.isotropic\) must be true or false"),
    ({"gradient": {"weight": 0.0, "order": 3}}, r"order must be 1 \(gradient\) or 2 \(Laplacian\), got 3"),
    ({"transform_l1": {"weight": 0.0, "transform": "fft"}}, r"unknown sparsifying transform 'fft'"),
    ({"symmetry": {"weight": 0.0, "order": 2.5}}, r"rotation order must be a whole number >= 1.*2\.5"),
    ({"volume": {"weight": 0.0, "fraction": -0.1}}, r"positive volume fraction, got -0\.1"),
    ({"l1": {"weight": 0.0, "scale": 2}}, r"bad options for prior 'l1'.*scale"),
    ({"learned": {"weight": 0.0, "mode": "nonsense"}}, r"unknown learned-prior mode 'nonsense'"),
    ({"learned": {"weight": 0.0, "refresh": 0}}, r"refresh must be a whole number >= 1.*got 0"),
    ({"learned": {"weight": 0.0, "wieghts": "x"}}, r"bad options for prior 'learned'.*wieghts"),
])
def test_options_of_a_prior_of_weight_0_are_checked(spec, match):
    """A prior of weight 0 was skipped before its options were looked at: ``solver.priors.tv={weight: 0,
    isotropc: true}`` (a typo) or a nonsense value was accepted without a word, and failed only once the weight
    was raised."""
    with pytest.raises(ValueError, match=match):
        build_priors(spec, volume_fraction=0.2)


def test_a_prior_of_weight_0_needs_nothing_an_active_one_needs():
    """Off priors stay off without what only an active one needs: the volume prior's measured fraction, a declared
    symmetry (the solver configs' defaults declare none), the learned prior's weights file (nothing is loaded)."""
    spec = {"volume": {"weight": 0.0}, "symmetry": {"weight": 0.0, "plane_normal": None, "axis": None, "order": 1},
            "learned": {"weight": 0.0, "weights": "no_such_weights_file.pt", "refresh": 10, "mode": "red",
                        "flips": False},
            "gradient": {"weight": 0.0, "order": 1}, "tv": 0, "binary": {"weight": 0.0}}
    assert build_priors(spec) == []
