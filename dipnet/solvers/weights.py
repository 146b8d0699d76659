"""Prior weights chosen from the data: the discrepancy principle.

A prior whose weight is ``"auto"`` in the solver's ``priors`` gets it from the measurement's
noise level (Morozov's discrepancy principle): the largest weight whose solution explains the
data no better than the noise allows, ``D(x_lambda) <= tau^2 delta^2``, where ``D`` is the
solver's data term (the weighted squared relative residual of
:class:`~dipnet.solvers.optimize.DataTerm`) and ``delta^2`` its value for the noise alone
(:func:`noise_level`). Larger weights give smoother shapes and larger residuals, so noisier
data get larger weights; data whose noise lies below what the grid can reproduce (noise-free
simulations: the voxel discretisation leaves a relative residual near 1%) get the floor
weight, the smallest of the ladder.

The search is a continuation down a geometric ladder (:class:`WeightRule`): a few warm-started
steps per rung from the largest weight down, stopped at the first rung whose residual reaches
the target; the weight is then interpolated between that rung and the one before it (linear in
``log w`` against ``log D``) and the solver's main run starts from the last rung's state with
it. Cost: ``steps`` solver steps per rung visited, on the full grid.

``delta^2`` counts the slabs the object fills (volume above ``hull_tol`` of the profile's
largest): the preprocessing's monotone fit of each dip's volume curve leaves the empty slabs
at exactly 0, so they hold no noise, and counting their sigma would set the target at about
twice the residual of the true shape (measured on the bundled meshes at 30 dB). With no
per-slab sigma the noise is estimated from the profiles
(:func:`~dipnet.evaluation.consistency.estimate_slab_sigma`, a high-pass of each profile),
which sees white noise but underestimates the smooth, correlated noise of interpolated level
readings, so such data get smaller weights than their noise deserves.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch

AUTO = "auto"
RULES = ("discrepancy",)


@dataclass(frozen=True)
class WeightRule:
    """How ``"auto"`` prior weights are chosen (:class:`DiscrepancyUpdate`).

    Args:
        rule: ``"discrepancy"`` (the only rule).
        tau: the residual target is ``tau`` times the noise's relative residual.
        start: the weight of the first step (and of a coarse stage).
        floor, largest: the weight stays in ``[floor, largest]``.
        every: steps between updates.
        until: share of the run (0..1) during which the weight is updated.
        gain: exponent of the update ``(target / residual)^gain``.
        max_factor: the most one update changes the weight by (> 1).
    """

    rule: str = "discrepancy"
    tau: float = 1.0
    start: float = 1e-3
    floor: float = 1e-4
    largest: float = 1e-1
    every: int = 10
    until: float = 0.6
    gain: float = 1.0
    max_factor: float = 2.0

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"unknown weight rule {self.rule!r}; choose one of {RULES}")
        if not (self.tau > 0 and 0 < self.floor <= self.start <= self.largest and int(self.every) >= 1
                and 0 <= self.until <= 1 and self.gain > 0 and self.max_factor > 1):
            raise ValueError("the weight rule needs tau > 0, 0 < floor <= start <= largest, every >= 1, "
                             f"0 <= until <= 1, gain > 0 and max_factor > 1, got {self}")


def auto_names(spec: Mapping[str, Mapping]) -> list[str]:
    """Names of the priors of ``spec`` (``{name: {"weight": w, ...}}``) whose weight is ``"auto"``."""
    return [name for name, options in spec.items()
            if (options if isinstance(options, str) else dict(options).get("weight")) == AUTO]


def with_weight(spec: Mapping[str, Mapping], weight: float) -> dict[str, dict]:
    """``spec`` with every ``"auto"`` weight replaced by ``weight``."""
    out = {}
    for name, options in spec.items():
        options = {"weight": options} if isinstance(options, (int, float, str)) else dict(options)
        if options.get("weight") == AUTO:
            options["weight"] = weight
        out[name] = options
    return out


def noise_level(target: torch.Tensor, sigma: torch.Tensor | None, weight: torch.Tensor, rel_tol: float = 0.005
                ) -> tuple[float, str]:
    """``(delta^2, source)``: the data term the noise alone gives (see the module docstring).

    Args:
        target: measured slab volumes ``(K, M)``, mm^3.
        sigma: their noise sigma ``(K, M)`` mm^3, or ``None`` (then estimated from ``target``).
        weight: the data term's normalised weights ``(K, M)`` (``sum weight * target^2 = 1``).
        rel_tol: a slab counts when its volume exceeds this share of its profile's largest.

    Returns:
        ``delta^2`` (dimensionless) and ``"sigma"`` or ``"estimated"``.
    """
    # imported here: dipnet.evaluation imports dipnet.solvers
    from dipnet.evaluation.consistency import estimate_slab_sigma

    if sigma is None:
        sigma, source = torch.full_like(target, estimate_slab_sigma(target)), "estimated"
    else:
        source = "sigma"
    filled = target > rel_tol * target.abs().amax(dim=1, keepdim=True)
    return float((weight.double() * sigma.double().pow(2))[filled].sum()), source


class DiscrepancyUpdate:
    """A ``before_step`` hook that moves the ``"auto"`` weights toward the discrepancy principle.

    Every :attr:`WeightRule.every` steps during the first :attr:`WeightRule.until` of a run it
    evaluates the data term ``D`` of the current occupancy and multiplies the weights by
    ``(tau^2 delta^2 / D)^gain``, that factor clipped to ``[1 / max_factor, max_factor]`` and
    the weight to ``[floor, largest]``: a residual below the noise raises the weight, one above
    lowers it. The rest of the run keeps the last weight, so the result converges for one weight.

    Args:
        priors: the solver's ``[(name, weight, module)]`` list, updated in place.
        names: the priors whose weight is chosen.
        residual: returns the current data term ``D``.
        noise: the noise's data term ``delta^2`` and its source (:func:`noise_level`).
        rule: the :class:`WeightRule`.
    """

    def __init__(self, priors: list, names: list[str], residual: Callable[[], float], noise: tuple[float, str],
                 rule: WeightRule) -> None:
        self.priors, self.names, self.residual, self.rule = priors, set(names), residual, rule
        self.goal, self.noise_source = rule.tau**2 * max(noise[0], 0.0), noise[1]
        self.weight = rule.start
        self.steps = 0
        self.trace: list[list[float]] = []  # [step, weight, relative residual] at every update
        self._set(self.weight)

    def _set(self, weight: float) -> None:
        self.weight = weight
        self.priors[:] = [(n, weight if n in self.names else w, m) for n, w, m in self.priors]

    def __call__(self, fraction: float) -> None:
        step, self.steps = self.steps, self.steps + 1
        if step == 0 or step % self.rule.every or fraction >= self.rule.until:
            return
        d = self.residual()
        factor = (self.goal / d) ** self.rule.gain if d > 0 else self.rule.max_factor
        factor = min(max(factor, 1.0 / self.rule.max_factor), self.rule.max_factor)
        self._set(min(max(self.weight * factor, self.rule.floor), self.rule.largest))
        self.trace.append([step, self.weight, math.sqrt(max(d, 0.0))])

    def record(self, final_residual: float) -> dict:
        """The choice and its reason (for ``Reconstruction.info`` and ``metrics.json``), given the
        data term ``D`` of the final result."""
        rule, reached = self.rule, final_residual > self.goal
        if self.weight <= rule.floor * (1 + 1e-9) and reached:
            why = "the noise lies below the residual the floor weight reaches (noise-free data): floor weight"
        elif self.weight >= rule.largest * (1 - 1e-9) and not reached:
            why = "even the largest weight fits the data more closely than the noise: largest weight"
        else:
            why = "the weight whose solution's residual matches tau times the noise"
        return {"rule": rule.rule, "reason": why, "weight": self.weight, "tau": rule.tau,
                "noise_residual": math.sqrt(self.goal) / rule.tau, "target_residual": math.sqrt(self.goal),
                "residual_reached": math.sqrt(max(final_residual, 0.0)), "noise_source": self.noise_source,
                "updates": self.trace}
