"""The learned prior: regularisation by denoising (RED) with a 3D CNN trained on generated shapes.

``LearnedPrior(o) = 0.5 <o, o - D(o)> / N^3`` with the denoiser ``D``
(:class:`~dipnet.solvers.denoiser.OccupancyDenoiser`, trained by ``scripts/train_prior.py``).
Its gradient is taken as the RED gradient ``(o - D(o)) / N^3`` (``D``'s Jacobian treated as
symmetric, ``D`` detached), which pulls the occupancy toward what the denoiser makes of it:
shapes like the generated training shapes (thin limbs and plates, flat faces, holes, cavities).

``D`` costs about as much as 10 dip-operator applications at 64^3, so it is evaluated every
``refresh`` calls and its output reused in between (lagged RED); ``refresh=1`` is exact RED. That lagged state
(the output and the call count, :meth:`LearnedPrior.lag_state`) goes into the optimisation's checkpoints, so a
resumed ``red`` solve is the uninterrupted one.

``mode="anchor"`` is the plug-and-play alternative: ``D`` is evaluated once, at the first call
(the solver's starting occupancy, e.g. a voxel result given as ``warm_start``), and the prior is
``0.5 mean (o - D(o_0))^2``: the solve refines the denoised start under the data term.

With ``flips`` the denoiser's output is averaged over the 8 reflections of the volume along its axes
(``D`` is applied to each reflected copy and reflected back): the dip directions have no preferred
axis, so this removes some of the network's own orientation bias at 8x the (still small) cost.

On a grid whose ``N`` is half the weights' (the voxel solver's coarse stage) ``D`` runs on the
volume upsampled (trilinear) to the weights' grid and its output is area-averaged back; any other
resolution, dimension or slab spacing raises :class:`~dipnet.solvers.denoiser.PriorMismatchError`.

The shipped weights were trained on dips over the whole hemisphere (41 Fibonacci directions), or over the 0-35 deg
tilts of the authors' rig (``denoiser64_tilt35``). Given a list of weights, the prior keeps, for each operator, the
one whose training plan leaves the band about the horizontal unmeasured nearest the dips' own
(:meth:`LearnedPrior.select_for`; ``conf/solver/voxel_learned.yaml`` lists both first stages). Dips that leave a much
wider band than the kept weights' plan give ``D`` inputs unlike its training ones:
:meth:`LearnedPrior.plan_warning` says so (solvers warn once per solve).
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.orientations import Reach, fibonacci_hemisphere, unmeasured_band_deg
from dipnet.core.flags import checked_flag
from dipnet.solvers.denoiser import OccupancyDenoiser, PriorMismatchError, load_weights_with_digest

#: Dips whose unmeasured band about the horizontal exceeds the training plan's by more than this (degrees) are
#: warned about (:meth:`LearnedPrior.plan_warning`)
PLAN_BAND_MARGIN_DEG = 10.0
#: Fewer dips than this share of the training plan's are warned about (:meth:`LearnedPrior.plan_warning`): the
#: weights trained on 41 dips were checked down to 20 (docs/design/learned-prior.md, "Other dip counts")
PLAN_DIPS_SHARE = 0.5
#: An object spanning less than this share of the training objects' ``fill`` is warned about
#: (:meth:`LearnedPrior.size_warning`): at half the working ball the shipped weights lost most of their gain
#: (docs/design/learned-prior.md, "Other dip counts and a smaller object"), at a quarter they did worse than the voxel
#: solver alone
PLAN_FILL_SHARE = 0.5

#: The spatial dims of a ``(B, C, N, N, N)`` volume to flip for each of its 8 axis reflections.
_REFLECTIONS = [dims for k in range(4) for dims in itertools.combinations((2, 3, 4), k)]


class LearnedPrior(nn.Module):
    """RED prior with a trained occupancy denoiser (see the module docstring).

    Args:
        weights: a weights file, or the name of weights shipped in ``dipnet/data/priors``
            (``None``: the first stage, ``denoiser64``; ``"denoiser64_stage2"``: the second, trained on
            the first round's results; see :func:`~dipnet.solvers.denoiser.weights_path`); or a list of them,
            of which each operator's dips keep one (:meth:`select_for`; the first until then).
        refresh: evaluate the denoiser every ``refresh`` calls (>= 1; ``red`` mode).
        mode: ``"red"`` or ``"anchor"`` (see the module docstring).
        flips: average ``D`` over the 8 axis reflections (see the module docstring).
    """

    MODES = ("red", "anchor")

    def __init__(self, weights: str | Path | None | Sequence[str | Path | None] = None, refresh: int = 10,
                 mode: str = "red", flips: bool = False) -> None:
        super().__init__()
        names = self.check_options(weights, refresh, mode, flips)
        self.mode, self.flips = mode, checked_flag("the learned prior's flips", flips)
        self.candidates = [(name, *_load(name)) for name in names]
        for _, denoiser, _, _ in self.candidates:
            for p in denoiser.parameters():
                p.requires_grad_(False)
        self._keep(0, None)
        self.refresh = int(refresh)
        self._calls, self._denoised = 0, None

    @classmethod
    def check_options(cls, weights: str | Path | None | Sequence[str | Path | None] = None, refresh: int = 10,
                      mode: str = "red", flips: bool = False) -> list:
        """Check the options as the constructor does, without loading any weights (a prior of weight 0 is checked
        this way: :func:`~dipnet.solvers.priors.build_priors`); returns the list of weights names.

        Raises:
            ValueError: a ``refresh``, ``mode``, ``flips`` or empty ``weights`` list the constructor refuses.
        """
        if isinstance(refresh, bool) or not isinstance(refresh, numbers.Integral) or refresh < 1:
            raise ValueError(f"refresh must be a whole number >= 1 (calls between denoiser evaluations), "
                             f"got {refresh!r}")
        if mode not in cls.MODES:
            raise ValueError(f"unknown learned-prior mode {mode!r}; choose one of {cls.MODES}")
        checked_flag("the learned prior's flips", flips)
        names = list(weights) if isinstance(weights, Sequence) and not isinstance(weights, str) else [weights]
        if not names:
            raise ValueError("the learned prior's weights: an empty list; give a weights file or shipped name, "
                             "or a list of them")
        return names

    def _keep(self, index: int, reason: str | None) -> None:
        """Use the candidate weights ``index``; :attr:`choice` records which and why (``reason`` ``None``: the only
        ones given), :attr:`digest` the sha256 of their file's bytes (12 hex characters)."""
        _, self.denoiser, self.meta, self.digest = self.candidates[index]
        self.n = int(self.meta["n"])
        self.choice = {"weights": self._name(index), "reason": reason}

    def select_for(self, directions: torch.Tensor) -> None:
        """Of several candidate weights, keep the one whose training plan leaves the band about the horizontal
        unmeasured (:func:`~dipnet.core.orientations.unmeasured_band_deg`) nearest that of 3D ``directions``
        ``(K, 3)`` (the first of equals; weights without a recorded plan count as the hemisphere's). One candidate,
        or 2D directions: nothing to choose."""
        if len(self.candidates) < 2 or directions.ndim != 2 or directions.shape[1] != 3:
            return
        band = unmeasured_band_deg(directions)
        bands = [_training_band_deg(meta) for _, _, meta, _ in self.candidates]
        index = min(range(len(bands)), key=lambda i: abs(bands[i] - band))
        others = ", ".join(f"{self._name(i)} {b:.0f}" for i, b in enumerate(bands) if i != index)
        reason = (f"the dips leave {band:.0f} deg about the horizontal unmeasured; the plan these weights were trained "
                  f"on {bands[index]:.0f} deg (the other candidates': {others})")
        self._keep(index, reason)

    def _name(self, index: int) -> str:
        """The candidate ``index``'s weights as given (``denoiser64`` for ``None``, the shipped first stage)."""
        name = self.candidates[index][0]
        return "denoiser64" if name is None else str(name)

    def check_operator(self, operator) -> None:
        """Refuse an operator whose grid or slabs differ from the weights' (called by the solvers).

        Raises:
            PriorMismatchError: another dimension, resolution or slab spacing.
        """
        self.select_for(operator.directions)
        self.check_grid(operator.grid.ndim, operator.grid.n, operator.n_slabs)

    def check_grid(self, ndim: int, n: int, n_slabs: int) -> None:
        """Refuse a grid of ``n`` voxels per axis in ``ndim`` dimensions with ``n_slabs`` slabs per profile that
        the weights were not trained for: the check of :meth:`check_operator` without an operator, which a job
        makes before it simulates or reads any dip.

        Raises:
            PriorMismatchError: another dimension, resolution or slab spacing.
        """
        self._check_grid(ndim, n)
        slabs = float(self.meta["n_slabs_per_voxel"]) * self.n  # a coarse stage keeps the fine grid's slabs
        if abs(n_slabs - slabs) > 1e-9:
            raise PriorMismatchError(
                f"the learned prior's weights were trained with {slabs:g} slabs on a {self.n}^3 grid, the operator "
                f"has {n_slabs} slabs on a {n}^{ndim} grid: train weights for it "
                "(scripts/train_prior.py) or drop the learned prior")

    def plan_warning(self, directions: torch.Tensor) -> str | None:
        """A warning when 3D ``directions`` ``(K, 3)`` leave a band about the horizontal unmeasured
        (:func:`~dipnet.core.orientations.unmeasured_band_deg`) more than :data:`PLAN_BAND_MARGIN_DEG` wider than
        the plan the weights were trained on (their meta's ``config``: ``dips`` Fibonacci directions, tilted at
        most ``max_tilt_deg``, 90 when not recorded), or when they are fewer than :data:`PLAN_DIPS_SHARE` of its
        ``dips``; else ``None``."""
        plan = _training_plan(self.meta)
        if directions.ndim != 2 or directions.shape[1] != 3 or plan is None:
            return None
        dips, tilt = plan
        trained, band = _training_band_deg(self.meta), unmeasured_band_deg(directions)
        where = "over the whole hemisphere" if tilt >= 90 else f"tilted 0-{tilt:g} deg"
        messages = []
        if band > trained + PLAN_BAND_MARGIN_DEG:
            messages.append(
                f"the learned prior's denoiser ({self.choice['weights']}) was trained on {dips} dips {where} (at "
                f"most {trained:.0f} deg from the horizontal unmeasured); these dips leave {band:.0f} deg unmeasured, "
                "so what it makes of the missing cone is a guess the data cannot check: on five validation meshes "
                "dipped at tilts of 0-35 deg, weights trained over the whole hemisphere gave 0.80-1.92 times "
                "solver=voxel's Chamfer; compare with solver=voxel, or train weights for the rig's tilts "
                "(scripts/train_prior.py --max-tilt-deg) and add them to solver.priors.learned.weights")
        fewest = math.floor(PLAN_DIPS_SHARE * dips)
        if len(directions) < fewest:
            messages.append(
                f"the learned prior's denoiser ({self.choice['weights']}) was trained on {dips} dips {where}, and "
                f"checked down to {fewest}; these are {len(directions)}: so few dips leave most of the shape open, "
                "and what the denoiser fills in there is a guess the data cannot check, so a shape far off passes as "
                "consistent (the hand at 64^3 from 6 dips: IoU 0.57, passing every check); add dips, or compare with "
                "solver=voxel")
        return "; and ".join(messages) or None

    def size_warning(self, fill: float) -> str | None:
        """A warning when the object spans less than :data:`PLAN_FILL_SHARE` of the share of the working ball the
        weights' training objects reached (their meta's ``config.fill``); ``fill``: the object's largest span over
        the working ball's diameter (:func:`object_fill`). ``None`` otherwise, or when the meta records no fill."""
        trained = (self.meta.get("config") or {}).get("fill")
        if not isinstance(trained, (int, float)) or not 0 < trained <= 1 or not fill < PLAN_FILL_SHARE * trained:
            return None
        return (f"the object spans at most {fill:.2f} of the working ball's diameter; the learned prior's denoiser "
                f"({self.choice['weights']}) was trained on objects reaching {trained:g} of it, "
                "and works at the voxels' "
                "scale, so on so few voxels it adds little or does harm (bracket_B66 at fill 0.25, 64^3, 41 dips: "
                "Chamfer 1.10 times solver=voxel's, consistent): give the grid the object's size (extent_mm=null with "
                f"the default fill, or an extent_mm near the object's span), or compare with solver=voxel")

    def _check_grid(self, ndim: int, n: int) -> None:
        trained = int(self.meta.get("ndim", 3))
        if ndim != trained:
            raise PriorMismatchError(
                f"the learned prior's weights were trained for a {self.n}^{trained} grid ({trained}D), not a "
                f"{ndim}D one ({n}^{ndim}): use {ndim}D weights, or drop the learned prior")
        if n not in (self.n, self.n // 2):
            raise PriorMismatchError(
                f"the learned prior's weights were trained for a {self.n}^{ndim} grid (or its {self.n // 2}^{ndim} "
                f"coarse stage), not {n}^{ndim}: train weights for this grid with scripts/train_prior.py --n {n}, "
                "or solve on the weights' grid")

    def denoise(self, occupancy: torch.Tensor) -> torch.Tensor:
        """``D(o)`` clipped to ``[0, 1]``, on the weights' grid (resampled for a coarse stage), same shape
        as ``occupancy``."""
        x = occupancy.detach().float()[None, None]
        n = occupancy.shape[-1]
        with torch.no_grad():
            if n != self.n:
                up = F.interpolate(x, size=(self.n,) * 3, mode="trilinear", align_corners=False)
                return F.avg_pool3d(self._apply(up), 2)[0, 0].to(occupancy.dtype)
            return self._apply(x)[0, 0].to(occupancy.dtype)

    def _apply(self, x: torch.Tensor) -> torch.Tensor:
        """``D(x)`` clipped to ``[0, 1]`` for ``(1, 1, N, N, N)``, averaged over the axis reflections
        when ``flips``."""
        if not self.flips:
            return self.denoiser(x).clamp(0, 1)
        total = sum(self.denoiser(x.flip(dims)).flip(dims) for dims in _REFLECTIONS)
        return (total / len(_REFLECTIONS)).clamp(0, 1)

    def anchor_at(self, occupancy: torch.Tensor) -> None:
        """In ``anchor`` mode, take ``D(occupancy)`` as the anchor now, as the first call would: the optimisation
        calls this with its stage's starting occupancy before a checkpoint moves the parameters on, so a resumed stage
        keeps the uninterrupted one's anchor (``red`` mode: nothing to do)."""
        if self.mode == "anchor":
            self._check_grid(occupancy.ndim, occupancy.shape[-1])
            self._denoised = self.denoise(occupancy)

    def lag_state(self) -> dict[str, Any] | None:
        """In ``red`` mode, what the next calls depend on beyond the occupancy, for a checkpoint
        (:class:`~dipnet.solvers.checkpoint.Checkpoint`): ``{"calls": calls so far, "denoised": the reused output
        D(o), grid.shape float32, or None before the first call}``; ``None`` in ``anchor`` mode (its anchor is D of
        the stage's start, :meth:`anchor_at`)."""
        if self.mode != "red":
            return None
        return {"calls": self._calls, "denoised": None if self._denoised is None else self._denoised.detach().clone()}

    def restore_lag(self, state: Mapping[str, Any]) -> None:
        """Take back a ``red`` mode :meth:`lag_state` (a resumed checkpoint's), so the next call reuses or refreshes
        D's output as the uninterrupted solve's would."""
        denoised = state["denoised"]
        self._calls, self._denoised = int(state["calls"]), None if denoised is None else denoised.detach().clone()

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        """``0.5 <o, o - D(o)> / N^3`` with gradient ``(o - D(o)) / N^3`` (``red``), or
        ``0.5 mean (o - D(o_0))^2`` (``anchor``)."""
        self._check_grid(occupancy.ndim, occupancy.shape[-1])
        stale = self._denoised is None or self._denoised.shape != occupancy.shape
        if stale or (self.mode == "red" and self._calls % self.refresh == 0):
            self._denoised = self.denoise(occupancy)
        self._calls += 1
        if self.mode == "anchor":
            return 0.5 * (occupancy - self._denoised).pow(2).mean()
        residual = occupancy.detach() - self._denoised
        inner = (occupancy * residual).mean()
        return inner - 0.5 * inner.detach()


def object_fill(profiles: torch.Tensor, slab_thickness: float, radius: float, rel_tol: float = 0.005) -> float:
    """The object's largest span (mm) over its dips ``profiles`` ``(K, M)``, between the first and last slab holding
    more than ``rel_tol`` of the dip's largest, over the working ball's diameter ``2 radius``: about the share of the
    ball the object fills (a job's ``fill``), a little less for dips that miss its longest direction."""
    p = torch.as_tensor(profiles).double()
    full = p > rel_tol * p.max(dim=1, keepdim=True).values.clamp(min=1e-300)
    if not full.any():
        return 0.0
    first = full.double().argmax(1)
    last = p.shape[1] - 1 - full.flip(1).double().argmax(1)
    spans = (last - first + 1).double()[full.any(1)] * float(slab_thickness)
    return float(spans.max()) / (2.0 * float(radius))


def _load(weights: str | Path | None) -> tuple[OccupancyDenoiser, dict, str]:
    """``(denoiser, meta, digest)`` of ``weights`` (a path or shipped name), the file read once
    (:func:`~dipnet.solvers.denoiser.load_weights_with_digest`): ``digest`` is the sha256 (12 hex characters) of the
    bytes loaded: weights retrained under the same name are other weights."""
    denoiser, meta, sha256 = load_weights_with_digest(weights)
    return denoiser, meta, sha256[:12]


def _training_plan(meta: dict) -> tuple[int, float] | None:
    """``(dips, max tilt in deg)`` of the plan weights were trained on (their meta's ``config``; the tilt 90 when not
    recorded), or ``None`` when the meta records no plan."""
    config = meta.get("config") or {}
    dips, tilt = config.get("dips"), config.get("max_tilt_deg", 90.0)
    if not isinstance(dips, int) or dips < 1 or not isinstance(tilt, (int, float)) or not 0 < tilt <= 90:
        return None
    return dips, float(tilt)


def _training_band_deg(meta: dict) -> float:
    """The band about the horizontal (deg) that the training plan of weights with ``meta`` leaves unmeasured (that of
    41 Fibonacci directions over the hemisphere when the meta records no plan)."""
    dips, tilt = _training_plan(meta) or (41, 90.0)
    plan = fibonacci_hemisphere(dips) if tilt >= 90 else Reach(tilt_range_deg=(0.0, tilt)).uniform(dips)
    return unmeasured_band_deg(plan)
