"""Neural occupancy fields: coordinate encodings and an MLP, in plain torch (CPU friendly).

Coordinates are normalised: the grid cube is ``[-1, 1]^d`` (``x / (extent / 2)``), points are
``(P, d)`` ordered ``(x, y[, z])``. :class:`OccupancyField` maps points to occupancy logits
``(P,)``; the occupancy is their sigmoid.

Encodings (:func:`make_encoding`, selected by ``{"type": name, **options}``):

* ``fourier``: random Fourier features ``[sin 2 pi B x, cos 2 pi B x]`` with Gaussian ``B``
  (Tancik et al. 2020);
* ``positional``: NeRF's axis-aligned ``sin / cos(2^k pi x)`` ladder;
* ``densegrid``: multi-resolution dense feature grids with multilinear interpolation
  (Mueller et al. 2022's multi-resolution grid without the hashing, see
  :class:`DenseGridEncoding`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.counts import is_real, whole_number
from dipnet.core.flags import checked_flag
from dipnet.solvers.priors import rotation_order, symmetry_maps



class FourierFeatures(nn.Module):
    """Random Fourier features.

    Args:
        ndim: 2 or 3.
        n_features: number of frequencies (output ``2 n_features (+ ndim)``), a whole number >= 1.
        scale: standard deviation of the frequencies, in cycles per unit of the normalised
            cube (``scale=4`` ~ features down to a quarter of the half-width); finite and > 0.
        include_input: append the raw coordinates (true or false).
    """

    def __init__(self, ndim: int, n_features: int = 128, scale: float = 4.0, include_input: bool = True) -> None:
        super().__init__()
        n_features = whole_number("the fourier encoding's n_features", n_features, low=1)
        if not is_real(scale) or not 0 < scale < math.inf:
            raise ValueError(f"the fourier encoding's scale must be a finite number > 0 (the frequencies' standard "
                             f"deviation, cycles per half-width), got {scale!r}")
        self.register_buffer("freqs", torch.randn(ndim, int(n_features)) * float(scale))
        self.include_input = checked_flag("the fourier encoding's include_input", include_input)
        self.out_dim = 2 * int(n_features) + (ndim if include_input else 0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        proj = 2 * math.pi * x @ self.freqs.to(x.dtype)
        parts = [torch.sin(proj), torch.cos(proj)] + ([x] if self.include_input else [])
        return torch.cat(parts, dim=-1)


class PositionalEncoding(nn.Module):
    """``[x, sin(2^k pi x), cos(2^k pi x)]`` for ``k = 0 .. n_frequencies - 1``, per axis (``n_frequencies`` a whole
    number >= 0; 0: the coordinates alone)."""

    def __init__(self, ndim: int, n_frequencies: int = 6) -> None:
        super().__init__()
        n_frequencies = whole_number("the positional encoding's n_frequencies", n_frequencies, low=0)
        self.register_buffer("scales", math.pi * 2.0 ** torch.arange(int(n_frequencies), dtype=torch.float32))
        self.out_dim = ndim * (1 + 2 * int(n_frequencies))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        proj = (x[..., None] * self.scales.to(x.dtype)).flatten(-2)
        return torch.cat([x, torch.sin(proj), torch.cos(proj)], dim=-1)


class DenseGridEncoding(nn.Module):
    """Multi-resolution dense feature grids with multilinear interpolation.

    Level ``l`` is a learnable grid of ``R_l^d`` feature vectors spanning the cube (values at
    cell centres, ``grid_sample`` with ``align_corners=False`` and border padding); the
    resolutions grow geometrically from ``base_resolution`` to ``max_resolution`` and the
    levels' features are concatenated. This is the hash grid of Mueller et al. (2022) without
    hashing: at the resolutions of dip reconstructions (<= 128^3) every level fits in memory,
    and ``grid_sample`` (one fused kernel per level, forward and backward) is several times
    faster on CPU than hashed gathers.

    Args:
        ndim: 2 or 3.
        levels: number of resolutions.
        features: features per level (output ``levels * features``).
        base_resolution, max_resolution: coarsest and finest cells per axis.
        init_scale: features start uniform in ``[-init_scale, init_scale]`` (finite, > 0).

    Every count is a whole number (``2.5``, ``True`` or ``"4"`` are refused, naming the option).
    """

    def __init__(self, ndim: int, levels: int = 6, features: int = 2, base_resolution: int = 4,
                 max_resolution: int = 64, init_scale: float = 1e-4) -> None:
        super().__init__()
        levels = whole_number("the densegrid encoding's levels", levels, low=1)
        features = whole_number("the densegrid encoding's features", features, low=1)
        base_resolution = whole_number("the densegrid encoding's base_resolution", base_resolution, low=2)
        max_resolution = whole_number("the densegrid encoding's max_resolution", max_resolution, low=2)
        if max_resolution < base_resolution:
            raise ValueError(f"densegrid needs base_resolution <= max_resolution (max_resolution null: the grid's N), "
                             f"got base_resolution {base_resolution} and max_resolution {max_resolution}")
        if not is_real(init_scale) or not 0 < init_scale < math.inf:
            raise ValueError(f"the densegrid encoding's init_scale must be a finite number > 0, got {init_scale!r}")
        self.ndim, self.features = ndim, int(features)
        growth = (max_resolution / base_resolution) ** (1 / max(levels - 1, 1))
        self.resolutions = [round(base_resolution * growth**i) for i in range(int(levels))]
        self.grids = nn.ParameterList(
            nn.Parameter((torch.rand(1, self.features, *([r] * ndim)) * 2 - 1) * init_scale) for r in self.resolutions)
        self.out_dim = len(self.resolutions) * self.features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pts = x.reshape(1, -1, *([1] * (self.ndim - 1)), self.ndim)
        parts = [F.grid_sample(g, pts.to(g.dtype), mode="bilinear", padding_mode="border", align_corners=False)
                 .reshape(self.features, -1) for g in self.grids]
        return torch.cat(parts).T.to(x.dtype)


ENCODINGS: dict[str, type[nn.Module]] = {
    "fourier": FourierFeatures,
    "positional": PositionalEncoding,
    "densegrid": DenseGridEncoding,
}


def make_encoding(ndim: int, spec: Mapping | None) -> nn.Module:
    """An encoding from ``{"type": name, **options}`` (names in :data:`ENCODINGS`)."""
    spec = dict(spec or {"type": "densegrid"})
    kind = spec.pop("type", "densegrid")
    if kind not in ENCODINGS:
        raise ValueError(f"unknown field encoding {kind!r}; choose one of {sorted(ENCODINGS)}")
    try:
        return ENCODINGS[kind](ndim, **spec)
    except TypeError as exc:
        raise ValueError(f"bad options for encoding {kind!r}: {exc}") from exc


class OccupancyField(nn.Module):
    """``logit(x) = MLP(encoding(S(x)))``; the occupancy is ``sigmoid(logit)``.

    Args:
        ndim: 2 or 3.
        encoding: encoding spec for :func:`make_encoding`.
        hidden_width, hidden_layers: the MLP (ReLU).
        symmetry: optional built-in symmetry ``{"plane_normal": n, "axis": a, "order": k}``
            (as :class:`~dipnet.solvers.priors.SymmetryPrior`). A mirror plane folds the input
            (``x -> x - 2 min(0, x.n) n``, one evaluation); a ``k``-fold rotation averages the
            logits over the ``k`` rotated copies of the input (``k`` evaluations), so the field
            is exactly symmetric and stays continuous.
    """

    def __init__(self, ndim: int, encoding: Mapping | None = None, hidden_width: int = 64, hidden_layers: int = 2,
                 symmetry: Mapping | None = None) -> None:
        super().__init__()
        self.ndim = ndim
        self.encoding = make_encoding(ndim, encoding)
        layers: list[nn.Module] = []
        width = self.encoding.out_dim
        for _ in range(int(hidden_layers)):
            layers += [nn.Linear(width, int(hidden_width)), nn.ReLU()]
            width = int(hidden_width)
        self.head = nn.Linear(width, 1)
        self.mlp = nn.Sequential(*layers, self.head)
        self._setup_symmetry(symmetry)

    def _setup_symmetry(self, symmetry: Mapping | None) -> None:
        sym = dict(symmetry or {})
        normal, axis, order = sym.get("plane_normal"), sym.get("axis"), rotation_order(sym.get("order", 1))
        unknown = set(sym) - {"plane_normal", "axis", "order"}
        if unknown:
            raise ValueError(f"unknown symmetry options {sorted(unknown)}; use plane_normal, axis, order")
        maps = symmetry_maps(self.ndim, normal, axis, order)  # validates
        self.fold = normal is not None
        n = torch.as_tensor(normal if self.fold else [0.0] * self.ndim, dtype=torch.float32)
        self.register_buffer("plane_normal", n / n.norm() if self.fold else n)
        rotation = maps[-1] if order > 1 else torch.eye(self.ndim, dtype=torch.float64)
        powers = [torch.linalg.matrix_power(rotation, k) for k in range(order)]
        self.register_buffer("rotations", torch.stack(powers).to(torch.float32))  # (k, d, d)

    def set_output_bias(self, logit: float) -> None:
        """Start the field at a uniform occupancy ``sigmoid(logit)`` (last layer weights zeroed
        would stop learning, so only the bias moves)."""
        with torch.no_grad():
            self.head.bias.fill_(float(logit))

    def _symmetric_inputs(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The inputs whose logits are averaged: each rotated copy, folded by the mirror."""
        inputs = []
        for rot in self.rotations:
            y = x @ rot.T.to(x.dtype) if len(self.rotations) > 1 else x
            if self.fold:
                n = self.plane_normal.to(x.dtype)
                y = y - 2 * torch.clamp(y @ n, max=0)[:, None] * n
            inputs.append(y)
        return inputs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits ``(P,)`` at normalised points ``x`` ``(P, d)``."""
        inputs = self._symmetric_inputs(x)
        if len(inputs) == 1:
            return self.mlp(self.encoding(inputs[0])).squeeze(-1)
        return torch.stack([self.mlp(self.encoding(y)).squeeze(-1) for y in inputs]).mean(0)
