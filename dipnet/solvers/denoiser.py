"""The learned prior's network: a small 3D U-Net denoiser of occupancy volumes, and its weights file.

:class:`OccupancyDenoiser` maps a soft occupancy ``(B, 1, N, N, N)`` (a reconstruction with the
artifacts of few dips) to a cleaner one, ``D(x) = x + r(x)``: two 2x down-samplings (channels
``c, 2c, 4c``), two 3^3 convolutions per level, skip connections, a residual ``r`` from the last
convolution (initialised to 0, so an untrained net is the identity). ``N`` must be divisible by 4.

Weights file: one ``torch.save`` dict ``{"format": WEIGHTS_FORMAT, "state_dict": ..., "meta": ...}``
with ``meta`` = ``{"n", "channels", "n_slabs_per_voxel", "ndim", ...}`` (the grid and operator the
weights were trained for, and how they were made); a JSON copy of ``meta`` sits next to it.
"""

from __future__ import annotations

import hashlib
import io
import math
import numbers
import pickle
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.strict_json import write_json

WEIGHTS_FORMAT = "dipnet-occupancy-denoiser-1"
#: The folder of the weights shipped in the package (see docs/guide/solvers.md, "Learned prior").
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "data" / "priors"
#: The first-stage weights (``weights: null``): D of a plain voxel reconstruction.
SHIPPED_WEIGHTS = SHIPPED_DIR / "denoiser64.pt"

#: What a weights file's meta must hold: the grid and operator the weights were trained for, and the width.
META_KEYS = ("n", "ndim", "n_slabs_per_voxel", "channels")


class PriorWeightsError(ValueError):
    """The learned prior's weights file is missing, unreadable or not a dipnet denoiser."""


class PriorMismatchError(PriorWeightsError):
    """The weights were trained for another grid resolution or operator than the one solved on."""


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(c_in, c_out, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv3d(c_out, c_out, 3, padding=1), nn.ReLU(inplace=True))


class OccupancyDenoiser(nn.Module):
    """``D(x) = x + r(x)``: a 3-level 3D U-Net residual (see the module docstring).

    Args:
        channels: ``c``, channels of the finest level (``2c``, ``4c`` below).
    """

    def __init__(self, channels: int = 8) -> None:
        super().__init__()
        c = int(channels)
        if c < 1:
            raise ValueError(f"channels must be positive, got {channels}")
        self.channels = c
        self.down0, self.down1, self.bottom = _block(1, c), _block(c, 2 * c), _block(2 * c, 4 * c)
        self.up1, self.up0 = _block(6 * c, 2 * c), _block(3 * c, c)
        self.out = nn.Conv3d(c, 1, 3, padding=1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 1, N, N, N)`` -> same shape (``N % 4 == 0``)."""
        if x.ndim != 5 or x.shape[1] != 1 or x.shape[-1] % 4:
            raise ValueError(f"the denoiser takes (B, 1, N, N, N) with N divisible by 4, got {tuple(x.shape)}")
        a = self.down0(x)
        b = self.down1(F.max_pool3d(a, 2))
        c = self.bottom(F.max_pool3d(b, 2))
        b = self.up1(torch.cat([b, F.interpolate(c, scale_factor=2, mode="nearest")], dim=1))
        a = self.up0(torch.cat([a, F.interpolate(b, scale_factor=2, mode="nearest")], dim=1))
        return x + self.out(a)


def save_weights(model: OccupancyDenoiser, path: str | Path, meta: dict) -> Path:
    """Write ``model``'s weights with ``meta`` (must hold ``n``, ``ndim``, ``n_slabs_per_voxel``) to
    ``path`` and ``meta`` as JSON to ``path.with_suffix(".json")``."""
    missing = set(META_KEYS) - {"channels"} - set(meta)
    if missing:
        raise ValueError(f"weights meta lacks {sorted(missing)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "channels": model.channels}
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    torch.save({"format": WEIGHTS_FORMAT, "state_dict": state, "meta": meta}, path)
    write_json(path.with_suffix(".json"), meta, indent=1, sort_keys=True)
    return path


def shipped_names() -> list[str]:
    """The names of the weights shipped in :data:`SHIPPED_DIR` (file stems)."""
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.pt"))


def weights_path(weights: str | Path | None) -> Path:
    """The file of ``weights``: ``None`` is :data:`SHIPPED_WEIGHTS`, a bare name (no folder, no
    suffix, e.g. ``"denoiser64_stage2"``) a file shipped in :data:`SHIPPED_DIR`, anything else a path."""
    if weights is None:
        return SHIPPED_WEIGHTS
    path = Path(weights)
    if path.name == str(weights) and not path.suffix:
        return SHIPPED_DIR / f"{path.name}.pt"
    return path


def existing_weights_path(weights: str | Path | None) -> Path:
    """:func:`weights_path` of ``weights``, checked to exist.

    Raises:
        PriorWeightsError: the file is missing, or is a folder.
    """
    path = weights_path(weights)
    if path.is_dir():
        inside = sorted(p.name for p in path.glob("*.pt"))
        raise PriorWeightsError(f"learned-prior weights {path} is a folder, not a weights file: give the .pt file"
                                + (f" in it ({', '.join(inside[:5])})" if inside else " (it holds no .pt file)"))
    if not path.is_file():
        raise PriorWeightsError(f"learned-prior weights not found: {path} (train them with scripts/train_prior.py, "
                                f"pass weights: null for the shipped first stage, "
                                f"or a shipped name: {shipped_names()})")
    return path


def load_weights(path: str | Path | None = None) -> tuple[OccupancyDenoiser, dict]:
    """``(model in eval mode, meta)`` from a weights file or shipped name (see :func:`weights_path`).

    Raises:
        PriorWeightsError: the file is missing, unreadable, not a dipnet denoiser, or holds a NaN or
            infinite value.
    """
    model, meta, _ = load_weights_with_digest(path)
    return model, meta


def load_weights_with_digest(path: str | Path | None = None) -> tuple[OccupancyDenoiser, dict, str]:
    """``(model in eval mode, meta, sha256)`` from a weights file or shipped name (see :func:`weights_path`):
    :func:`load_weights` and the sha256 (64 hex characters) of the file's bytes, read once, so the digest is that
    of the very bytes loaded (a file replaced between two reads cannot give the weights of one and the digest of
    the other).

    Raises:
        PriorWeightsError: as :func:`load_weights`.
    """
    path = existing_weights_path(path)
    try:
        data = path.read_bytes()
        saved = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:  # torch's message advises weights_only=False: unsafe for a foreign file
        raise PriorWeightsError(f"learned-prior weights {path} are not a dipnet denoiser weights file (format "
                                f"{WEIGHTS_FORMAT}): torch cannot read it as saved tensors") from exc
    except Exception as exc:  # torch raises many types for a damaged file
        raise PriorWeightsError(f"learned-prior weights {path} are unreadable ({type(exc).__name__}: {exc})") from exc
    if not isinstance(saved, dict) or saved.get("format") != WEIGHTS_FORMAT:
        raise PriorWeightsError(f"{path} is not a dipnet denoiser weights file (format {WEIGHTS_FORMAT})")
    meta = dict(saved.get("meta") or {})
    missing = sorted(set(META_KEYS) - set(meta))
    if missing:
        raise PriorWeightsError(f"learned-prior weights {path}: their meta lacks {', '.join(missing)} (the grid, "
                                "operator and network they were trained for): not a complete dipnet denoiser file")
    bad = _bad_meta(meta)
    if bad:
        raise PriorWeightsError(f"learned-prior weights {path}: their meta gives {bad} (a weights file holds n a "
                                "positive multiple of 4, ndim 2 or 3, a positive n_slabs_per_voxel and channels): "
                                "a damaged or hand-edited file; retrain them (scripts/train_prior.py)")
    try:
        model = OccupancyDenoiser(int(meta["channels"]))
        model.load_state_dict(saved["state_dict"])
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise PriorWeightsError(f"learned-prior weights {path} do not fit the denoiser: {exc}") from exc
    bad = nonfinite_tensors(model)
    if bad:
        raise PriorWeightsError(f"learned-prior weights {path}: tensor {bad[0]} holds NaN or infinite values"
                                f"{f' (and {len(bad) - 1} more)' if len(bad) > 1 else ''}: damaged, or saved from a "
                                "diverged training; retrain them (scripts/train_prior.py, a lower --lr)")
    return model.eval(), meta, hashlib.sha256(data).hexdigest()


def _bad_meta(meta: dict) -> str:
    """The first of :data:`META_KEYS` whose value a weights file cannot hold (``key=value``), or ``""``: ``n`` a
    positive multiple of 4 (the U-Net's two poolings), ``ndim`` 2 or 3, ``n_slabs_per_voxel`` finite and positive,
    ``channels`` a positive integer."""
    def whole(value) -> bool:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)

    checks = {"n": lambda v: whole(v) and v > 0 and v % 4 == 0, "ndim": lambda v: whole(v) and v in (2, 3),
              "n_slabs_per_voxel": lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool)
              and math.isfinite(v) and v > 0,
              "channels": lambda v: whole(v) and v > 0}
    return next((f"{key}={meta[key]!r}" for key, ok in checks.items() if not ok(meta[key])), "")


def nonfinite_tensors(model: nn.Module) -> list[str]:
    """The names of ``model``'s parameters and buffers holding a NaN or infinite value (state-dict order)."""
    return [name for name, value in model.state_dict().items()
            if value.is_floating_point() and not bool(torch.isfinite(value).all())]
