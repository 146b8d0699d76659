"""The dip operator in deepinv's layout: exact adjoint, shapes, and deepinv's own adjointness test
(or, where deepinv cannot be imported, the named error of its extra)."""

from __future__ import annotations

import importlib

import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.optional import MissingExtraError
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.operators.deepinv_physics import deepinv_maps, dip_physics


def _operator():
    return make_operator(Grid(12, 3), fibonacci_hemisphere(7), 12)


def _deepinv_importable() -> bool:
    try:
        importlib.import_module("deepinv")
    except ImportError:
        return False
    return True


def test_maps_are_exact_adjoints_in_deepinv_layout():
    forward, adjoint = deepinv_maps(_operator())
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 1, 12, 12, 12, generator=gen, dtype=torch.float64)
    y = torch.randn(3, 1, 7, 12, generator=gen, dtype=torch.float64)
    ax = forward(x, extra="ignored")
    assert ax.shape == (3, 1, 7, 12) and ax.dtype == torch.float64
    lhs, rhs = (ax * y).sum(), (x * adjoint(y)).sum()
    assert abs(float(lhs - rhs)) <= 1e-10 * abs(float(lhs))
    with pytest.raises(ValueError, match="deepinv volumes"):
        forward(torch.zeros(12, 12, 12))
    with pytest.raises(ValueError, match="deepinv measurements"):
        adjoint(torch.zeros(1, 7, 12))


def test_deepinv_physics_passes_deepinv_adjointness_test():
    if not _deepinv_importable():
        with pytest.raises(MissingExtraError, match=r"dipnet\[learned\]"):
            dip_physics(_operator())
        return
    physics = dip_physics(_operator())
    x = torch.rand(2, 1, 12, 12, 12, dtype=torch.float64)
    assert float(physics.adjointness_test(x)) < 1e-10
    y = physics(x)
    assert y.shape == (2, 1, 7, 12)
    assert torch.allclose(physics.A_adjoint(y), deepinv_maps(_operator())[1](y))
