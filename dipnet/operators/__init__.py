"""Dip operator backends behind one interface (:class:`DipOperator`)."""

from __future__ import annotations

import torch

from dipnet.grid import Grid
from dipnet.operators.base import DipOperator
from dipnet.operators.rotate_sum import RotateSumOperator
from dipnet.operators.splat import SplatOperator

BACKENDS: dict[str, type[DipOperator]] = {
    "rotate_sum": RotateSumOperator,
    "splat": SplatOperator,
}

DEFAULT_BACKEND = "splat"


def make_operator(grid: Grid, directions: torch.Tensor, n_slabs: int | None = None,
                  backend: str = DEFAULT_BACKEND, **options) -> DipOperator:
    """Build the dip operator ``backend`` for ``grid`` and ``directions`` ``(K, d)``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown operator backend {backend!r}; choose one of {sorted(BACKENDS)}")
    return BACKENDS[backend](grid, directions, n_slabs, **options)


__all__ = ["BACKENDS", "DEFAULT_BACKEND", "DipOperator", "RotateSumOperator", "SplatOperator", "make_operator"]
