"""Priors (regularisers) on an occupancy volume, shared by the optimisation solvers.

Each prior is a small :class:`torch.nn.Module` ``prior(occupancy) -> scalar`` on one volume
``(N, N)`` or ``(N, N, N)`` (indexed ``[z, y, x]``, values in ``[0, 1]``). Every value is a
continuum integral measured in units of the grid cube (side 1), so a prior's weight means
the same at every resolution and in every unit system: with ``h = 1/N``,

* :class:`TotalVariation`: ``int |grad o| dx`` = ``h^(d-1) sum |D o|`` -- the surface area
  (perimeter in 2D) of a binary shape, in units of the cube's face;
* :class:`GradientPenalty`: ``int |grad o|^2 dx`` (``h^(d-2) sum (D o)^2``) or, with
  ``order=2``, ``int (lap o)^2 dx`` (``h^(d-4) sum (L o)^2``);
* :class:`SymmetryPrior`, :class:`L1Prior`, :class:`TransformL1Prior`, :class:`BinaryPrior`:
  ``int ... dx`` over the cube = means over voxels;
* :class:`VolumePrior`: ``(mean(o) / f - 1)^2``, the squared relative error of the volume
  against the measured volume fraction ``f`` (the object's volume / the cube's);
* :class:`~dipnet.solvers.learned.LearnedPrior` (``learned``): RED with a 3D CNN denoiser
  trained on generated shapes, ``0.5 <o, o - D(o)> / N^3`` (3D, on the weights' grid).

:func:`build_priors` turns a config dict ``{name: {"weight": w, **options}}`` into weighted
modules (weight 0 = off), e.g. ``{"tv": {"weight": 0.01}, "symmetry": {"weight": 1,
"plane_normal": [1, 0, 0]}}``.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.counts import is_real
from dipnet.core.flags import checked_flag
from dipnet.solvers.learned import LearnedPrior


def _spatial_dims(occupancy: torch.Tensor) -> tuple[int, ...]:
    if occupancy.ndim not in (2, 3):
        raise ValueError(f"priors take one 2D or 3D volume, got shape {tuple(occupancy.shape)}")
    return tuple(range(occupancy.ndim))


def _differences(occupancy: torch.Tensor) -> list[torch.Tensor]:
    """Forward differences along every axis, ``occupancy.shape`` each (0 in the last slice:
    Neumann boundary)."""
    return [torch.diff(occupancy, dim=d, append=occupancy.narrow(d, occupancy.shape[d] - 1, 1))
            for d in _spatial_dims(occupancy)]


class TotalVariation(nn.Module):
    """Total variation ``h^(d-1) sum |D o|`` (see the module docstring).

    Args:
        isotropic: ``sqrt(sum_axis (D_axis o)^2 + eps^2) - eps`` per voxel (rotation invariant;
            ``eps`` keeps the gradient finite at flat regions) instead of ``sum_axis |D_axis o|``.
        eps: smoothing of the isotropic norm (occupancy units).
    """

    def __init__(self, isotropic: bool = True, eps: float = 1e-3) -> None:
        super().__init__()
        self.isotropic = checked_flag("the tv prior's isotropic (solver.priors.tv.isotropic)", isotropic)
        self.eps = float(eps)

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        n = occupancy.shape[-1]
        grads = _differences(occupancy)
        if self.isotropic:
            total = (torch.sqrt(sum(g.pow(2) for g in grads) + self.eps**2) - self.eps).sum()
        else:
            total = sum(g.abs().sum() for g in grads)
        return total / n ** (occupancy.ndim - 1)


class GradientPenalty(nn.Module):
    """Quadratic smoothness: ``int |grad o|^2`` (``order=1``) or ``int (lap o)^2`` (``order=2``).

    The Laplacian is the ``2d + 1``-point stencil on interior voxels.
    """

    def __init__(self, order: int = 1) -> None:
        super().__init__()
        if order not in (1, 2):
            raise ValueError(f"gradient penalty order must be 1 (gradient) or 2 (Laplacian), got {order!r}")
        self.order = int(order)

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        dims, n, d = _spatial_dims(occupancy), occupancy.shape[-1], occupancy.ndim
        if self.order == 1:
            return sum(torch.diff(occupancy, dim=a).pow(2).sum() for a in dims) * float(n) ** (2 - d)
        lap = sum(torch.diff(occupancy, n=2, dim=a)[tuple(slice(None) if i == a else slice(1, -1) for i in dims)]
                  for a in dims)
        return lap.pow(2).sum() * float(n) ** (4 - d)


def _rotation_matrix(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """Rodrigues' rotation about unit ``axis`` (3,) by ``angle`` rad, ``(3, 3)``."""
    a = axis / axis.norm()
    cross = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def rotation_order(order) -> int:
    """``order`` (the ``n`` of an ``n``-fold rotation) as an int; a ``ValueError`` unless it is a whole number >= 1
    (``3.0`` is 3; ``2.5`` or ``True`` are refused rather than read as a 2- or 1-fold rotation)."""
    if not is_real(order) or not math.isfinite(order) \
            or int(order) != order or order < 1:
        raise ValueError(f"rotation order must be a whole number >= 1 (the n of an n-fold rotation), got {order!r}")
    return int(order)


def symmetry_maps(ndim: int, plane_normal: Sequence[float] | None = None, axis: Sequence[float] | None = None,
                  order: int = 1) -> list[torch.Tensor]:
    """The generators of a symmetry group as ``(d, d)`` float64 matrices acting on ``(x, y[, z])``.

    Args:
        ndim: 2 or 3.
        plane_normal: normal of a mirror plane (3D) / line (2D) through the centre.
        axis: rotation axis through the centre (3D; ignored in 2D, where rotations are about
            the centre).
        order: ``n`` of an ``n``-fold rotation (1 = none).
    """
    maps = []
    if plane_normal is not None:
        n = torch.as_tensor(plane_normal, dtype=torch.float64)
        if n.shape != (ndim,) or n.norm() == 0 or not bool(torch.isfinite(n).all()):
            raise ValueError(f"plane_normal must be a non-zero, finite {ndim}-vector, got {plane_normal!r}")
        n = n / n.norm()
        maps.append(torch.eye(ndim, dtype=torch.float64) - 2 * torch.outer(n, n))
    order = rotation_order(order)
    if order > 1:
        angle = 2 * math.pi / order
        if ndim == 2:
            c, s = math.cos(angle), math.sin(angle)
            maps.append(torch.tensor([[c, -s], [s, c]], dtype=torch.float64))
        else:
            if axis is None:
                raise ValueError("an n-fold rotation in 3D needs its axis")
            ax = torch.as_tensor(axis, dtype=torch.float64)
            if ax.shape != (3,) or ax.norm() == 0 or not bool(torch.isfinite(ax).all()):
                raise ValueError(f"axis must be a non-zero, finite 3-vector, got {axis!r}")
            maps.append(_rotation_matrix(ax, angle))
    return maps


def symmetry_spec(plane_normal: Sequence[float] | None = None, axis: Sequence[float] | None = None,
                  order: int = 1) -> dict:
    """``{"plane_normal", "axis", "order"}`` with plain lists of floats (or ``None``) and an int: a declared
    symmetry as :func:`symmetry_maps` takes it, JSON-serialisable."""
    def vector(v):
        return None if v is None else [float(x) for x in v]

    return {"plane_normal": vector(plane_normal), "axis": vector(axis), "order": rotation_order(order)}


class SymmetryPrior(nn.Module):
    """Mean squared difference between the volume and its mirrored / rotated copies.

    The copies are resampled with ``grid_sample`` (trilinear / bilinear) about the grid
    centre; only voxels in the inscribed ball (whose images stay inside the grid) count.
    Mirror planes through the centre along grid axes and 2- or 4-fold rotations about a grid
    axis map voxel centres onto voxel centres, so an exactly symmetric volume scores 0; other
    maps interpolate.

    Args: see :func:`symmetry_maps` (``plane_normal``, ``axis``, ``order``).
    """

    def __init__(self, plane_normal: Sequence[float] | None = None, axis: Sequence[float] | None = None,
                 order: int = 1) -> None:
        super().__init__()
        self.plane_normal, self.axis, self.order = plane_normal, axis, rotation_order(order)
        if plane_normal is None and self.order == 1:
            raise ValueError("the symmetry prior needs a plane_normal and/or a rotation order > 1")
        self._cache: dict = {}

    def _grids(self, shape: tuple[int, ...], dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        key = (shape, dtype, device)
        if key not in self._cache:
            d, n = len(shape), shape[-1]
            axis = (torch.arange(n, dtype=torch.float64) + 0.5) * (2.0 / n) - 1.0
            pts = torch.stack(torch.meshgrid(*([axis] * d), indexing="ij")[::-1], dim=-1)  # (x, y[, z])
            mats = symmetry_maps(d, self.plane_normal, self.axis, self.order)
            grids = torch.stack([pts @ m.T for m in mats])  # (G, *shape, d)
            inside = (pts.norm(dim=-1) <= 1 - 1.0 / n).to(dtype)
            self._cache[key] = (grids.to(dtype=dtype, device=device), inside.to(device))
        return self._cache[key]

    def spec(self) -> dict:
        """The declared symmetry as ``{"plane_normal", "axis", "order"}`` (lists of floats or ``None``, an int):
        what :func:`symmetry_maps` takes, and what a result records (``info["symmetries"]``)."""
        return symmetry_spec(self.plane_normal, self.axis, self.order)

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        _spatial_dims(occupancy)
        grids, inside = self._grids(tuple(occupancy.shape), occupancy.dtype, occupancy.device)
        vol = occupancy.unsqueeze(0).unsqueeze(0).expand(grids.shape[0], 1, *occupancy.shape)
        moved = F.grid_sample(vol, grids, mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0]
        return ((moved - occupancy).pow(2) * inside).sum() / (inside.sum() * grids.shape[0])


class L1Prior(nn.Module):
    """Sparsity of the occupancy itself: ``mean |o|``."""

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        _spatial_dims(occupancy)
        return occupancy.abs().mean()


def dct_matrix(n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Orthonormal DCT-II matrix ``(n, n)``: row ``k`` is the ``k``-th cosine."""
    i = torch.arange(n, dtype=torch.float64)
    mat = torch.cos(math.pi * (i[None, :] + 0.5) * i[:, None] / n) * math.sqrt(2.0 / n)
    mat[0] /= math.sqrt(2.0)
    return mat.to(dtype)


def haar_matrix(n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Orthonormal multi-level Haar analysis matrix ``(n, n)``.

    Splits into averages and details while the length is even; rows are the coarsest
    averages first, then details from coarse to fine.
    """
    mat = torch.eye(n, dtype=torch.float64)
    length = n
    while length % 2 == 0 and length >= 2:
        half = length // 2
        step = torch.zeros(length, length, dtype=torch.float64)
        idx = torch.arange(half)
        step[idx, 2 * idx] = step[idx, 2 * idx + 1] = 1 / math.sqrt(2.0)
        step[half + idx, 2 * idx], step[half + idx, 2 * idx + 1] = 1 / math.sqrt(2.0), -1 / math.sqrt(2.0)
        mat[:length] = step @ mat[:length]
        length = half
    return mat.to(dtype)


class TransformL1Prior(nn.Module):
    """Compressed-sensing sparsity: ``mean |W o|`` over the coefficients of a separable
    orthonormal transform ``W`` (DCT-II or Haar wavelets), without the constant (DC) term,
    which is the total volume that the data fix anyway. Transforms are ``(N, N)`` matrices
    applied along each axis (fine up to ~128^3)."""

    TRANSFORMS = ("dct", "haar")

    def __init__(self, transform: str = "dct") -> None:
        super().__init__()
        if transform not in self.TRANSFORMS:
            raise ValueError(f"unknown sparsifying transform {transform!r}; choose one of {self.TRANSFORMS}")
        self.transform = transform
        self._cache: dict = {}

    def coefficients(self, occupancy: torch.Tensor) -> torch.Tensor:
        """Transform coefficients, same shape as ``occupancy``."""
        _spatial_dims(occupancy)
        key = (occupancy.shape[-1], occupancy.dtype, occupancy.device)
        if key not in self._cache:
            make = dct_matrix if self.transform == "dct" else haar_matrix
            self._cache[key] = make(key[0], occupancy.dtype).to(occupancy.device)
        mat = self._cache[key]
        out = occupancy
        for axis in range(occupancy.ndim):
            out = torch.movedim(torch.tensordot(mat, out, dims=([1], [axis])), 0, axis)
        return out

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        coef = self.coefficients(occupancy)
        dc = coef[(0,) * coef.ndim]
        return (coef.abs().sum() - dc.abs()) / coef.numel()


class BinaryPrior(nn.Module):
    """Binary-ness ``mean o (1 - o)``: zero exactly when every voxel is 0 or 1."""

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        _spatial_dims(occupancy)
        return (occupancy * (1 - occupancy)).mean()


class VolumePrior(nn.Module):
    """Total volume: ``(mean(o) / fraction - 1)^2``.

    Args:
        fraction: the object's volume as a fraction of the grid cube's volume (every measured
            profile sums to the object volume; solvers pass ``median profile sum / extent^d``).
    """

    def __init__(self, fraction: float) -> None:
        super().__init__()
        if not fraction > 0:
            raise ValueError(f"the volume prior needs a positive volume fraction, got {fraction!r}")
        self.fraction = float(fraction)

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        _spatial_dims(occupancy)
        return (occupancy.mean() / self.fraction - 1).pow(2)


PRIORS: dict[str, type[nn.Module]] = {
    "tv": TotalVariation,
    "gradient": GradientPenalty,
    "symmetry": SymmetryPrior,
    "l1": L1Prior,
    "transform_l1": TransformL1Prior,
    "binary": BinaryPrior,
    "volume": VolumePrior,
    "learned": LearnedPrior,
}


def prior_weight(name: str, weight: float) -> float:
    """The numeric weight of prior ``name`` as a float; ``ValueError`` for a negative, NaN or infinite one (a NaN
    passed a sign test and ended as "the loss became nan ... try a lower solver.lr")."""
    weight = float(weight)
    if weight < 0:
        raise ValueError(f"prior {name!r} has a negative weight {weight}")
    if not math.isfinite(weight):
        raise ValueError(f"prior {name!r} has weight {weight}: a weight is a finite number >= 0 (0 = off) or 'auto'")
    return weight


def checked_priors(name: str, spec):
    """``spec`` (the option ``name``: ``priors``, ``later_priors``), unless it is neither null nor a mapping
    ``{prior: options}``.

    Raises:
        ValueError: naming the option (was: ``solver.later_priors=5`` "'int' object has no attribute 'items'").
    """
    if spec is not None and not isinstance(spec, Mapping):
        raise ValueError(f"{name} must be null or a mapping {{prior: options}} with priors from {sorted(PRIORS)}, e.g. "
                         f"{{tv: {{weight: 1.0e-3}}}}, got {spec!r}")
    return spec


def build_priors(spec: Mapping[str, Mapping] | None, volume_fraction: float | None = None
                 ) -> list[tuple[str, float, nn.Module]]:
    """``[(name, weight, module)]`` for the priors of ``spec`` with a non-zero weight; the options of those of weight 0
    are checked all the same (:func:`check_off_prior`), so a misspelt or refused option fails whatever the weight.

    Args:
        spec: ``{name: {"weight": w, **options}}`` with names from :data:`PRIORS`; a bare
            number is a weight with default options.
        volume_fraction: measured object volume / grid cube volume, for the ``volume`` prior
            (when its options give no ``fraction``).
    """
    out = []
    for name, options in (spec or {}).items():
        if name not in PRIORS:
            raise ValueError(f"unknown prior {name!r}; choose from {sorted(PRIORS)}")
        options = {"weight": options} if isinstance(options, (int, float)) else dict(options)
        weight = prior_weight(name, options.pop("weight", 0.0))
        if weight == 0:  # off, but its options are checked as an active prior's (a typo is no less one at 0)
            check_off_prior(name, options)
            continue
        if name == "volume" and "fraction" not in options:
            if volume_fraction is None:
                raise ValueError("the volume prior needs the measured volume fraction")
            options["fraction"] = volume_fraction
        try:
            module = PRIORS[name](**options)
        except TypeError as exc:
            raise ValueError(f"bad options for prior {name!r}: {exc}") from exc
        out.append((name, weight, module))
    return out


def check_off_prior(name: str, options: Mapping) -> None:
    """Check the ``options`` (without ``weight``) of prior ``name`` at weight 0 as those of an active one: unknown
    names and refused values raise the same ``ValueError``. What only an active prior needs is not asked for: the
    ``volume`` prior's measured fraction, a declared symmetry (``symmetry``'s defaults declare none), the
    ``learned`` prior's weights file (:meth:`~dipnet.solvers.learned.LearnedPrior.check_options`, nothing loaded).
    """
    options = dict(options)
    cls = PRIORS[name]
    try:
        inspect.signature(cls).bind_partial(**options)  # unknown option names
        if name == "learned":
            LearnedPrior.check_options(**options)
            return
        if name == "symmetry" and options.get("plane_normal") is None:
            rotation_order(options.get("order", 1))  # none declared: only the order to check
            return
        if name == "volume":
            options.setdefault("fraction", 1.0)
        cls(**options)
    except TypeError as exc:
        raise ValueError(f"bad options for prior {name!r}: {exc}") from exc
