"""Prior weights chosen from the data: the discrepancy principle.

A prior whose weight is ``"auto"`` in the solver's ``priors`` gets it from the measurement's
noise level (Morozov's discrepancy principle): the weight whose solution leaves the data term
``D = tau^2 delta^2``, where ``D`` is the solver's data term (the weighted squared relative
residual of :class:`~dipnet.solvers.optimize.DataTerm`) and ``delta^2`` its value for the noise
alone (:func:`noise_level`). Larger weights give smoother shapes and larger residuals, so noisier
data get larger weights; data whose noise lies below what the grid can reproduce (noise-free
simulations: the voxel discretisation leaves a relative residual near 1% at 64^3) get the floor.

The search is one step (:meth:`WeightRule.next_weight`): the solver first runs with the weight
``start``, reads ``D``, takes ``start (tau^2 delta^2 / D)^(1 / slope)`` (``slope`` = the measured
``d log D / d log w``) and refits from the first solution at that weight for a share ``refit`` of
its steps (:meth:`~dipnet.solvers.optimize.OptimisationSolver.choose_weights`). A single step
from a converged solve: residuals read during a run lag the weight (the data term keeps falling
while the optimiser converges), which drove an update-as-you-go rule to the floor and a
warm-started ladder of short solves to weights three times too small.

``tau`` is 0.7, not 1: with ``N^3`` unknowns and a few thousand slab volumes the solution fits
part of the noise, so the residual at the best weight lies well below the noise (measured at 30 dB,
41 dips, 64^3: the true shape leaves 0.89 ``delta^2``, the Chamfer-best weight about 0.45; see
``docs/guide/solvers.md``).

An estimated noise only lowers the weight: the high-pass that estimates it also reads the
profiles' own curvature, which on noise-free data the grid reproduces well dominates it (the
torus at 32^3, 41 dips: weight 0.1 and Chamfer 0.0049 instead of 0.0017).

``delta^2`` counts the slabs the object fills (volume above ``rel_tol`` of the profile's
largest): the preprocessing's monotone fit of each dip's volume curve leaves the empty slabs
at exactly 0, so they hold no noise, and counting their sigma would set the target at about
twice the residual of the true shape. With no stated sigma the solvers take the one the raw
readings' own scatter gives (source ``"readings"``, :func:`dipnet.solvers.base.noise_sigma`; a
recording whose sensor states no noise), known as well as a stated one (:data:`KNOWN_NOISE`).
Without readings either, the noise is estimated from the profiles
(:func:`~dipnet.core.measurement.estimate_slab_sigma`, a high-pass of each profile),
which sees white noise but underestimates the smooth, correlated noise of interpolated level
readings (2.2-3.7 times at 64^3, 30 dB), so such data get smaller weights than their noise deserves.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import torch

from dipnet.core.measurement import estimate_slab_sigma, filled_slabs

AUTO = "auto"
RULES = ("discrepancy",)
#: The weight rule's numeric options: each must be a finite number.
NUMBERS = ("tau", "start", "floor", "largest", "slope", "tolerance", "refit", "refit_lr")
#: Noise sources (:func:`dipnet.solvers.base.noise_sigma`) known well enough to raise a prior's weight or license a
#: further round: a stated noise, or the readings' own scatter; not the profiles' estimate
KNOWN_NOISE = ("sigma", "readings")


@dataclass(frozen=True)
class WeightRule:
    """How ``"auto"`` prior weights are chosen (see the module docstring). Every option but ``rule`` is a finite
    number (an infinite one is refused).

    Args:
        rule: ``"discrepancy"`` (the only rule).
        tau: the residual target is ``tau`` times the noise's relative residual.
        start: the weight of the first solve.
        floor, largest: the chosen weight stays in ``[floor, largest]``.
        slope: ``d log D / d log w`` assumed for the step from the first solve's residual to the weight
            (measured 0.25-0.53 for the voxel solver at 64^3, 41 dips, 30 dB).
        tolerance: keep the first weight when ``|D / target - 1|`` is below this.
        refit: steps of the refit at the chosen weight, as a share of the solver's (last-stage) steps.
        refit_lr: the refit's learning rate as a share of the solver's.
    """

    rule: str = "discrepancy"
    tau: float = 0.7
    start: float = 1e-3
    floor: float = 1e-4
    largest: float = 1e-1
    slope: float = 0.35
    tolerance: float = 0.1
    refit: float = 0.35
    refit_lr: float = 0.3

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"unknown weight rule {self.rule!r}; choose one of {RULES}")
        if not (self.tau > 0 and 0 < self.floor <= self.start <= self.largest and self.slope > 0
                and self.tolerance >= 0 and 0 < self.refit <= 1 and self.refit_lr > 0):
            raise ValueError("the weight rule needs tau > 0, 0 < floor <= start <= largest, slope > 0, "
                             f"tolerance >= 0, 0 < refit <= 1 and refit_lr > 0, got {self}")
        infinite = [name for name in NUMBERS if not math.isfinite(getattr(self, name))]
        if infinite:  # tau = inf aims at an infinite data term (the largest weight), slope = inf never moves the start
            raise ValueError(f"the weight rule's {', '.join(infinite)} must be finite numbers, got {self}")

    @classmethod
    def from_options(cls, options: Mapping) -> "WeightRule":
        """The rule of a config's ``weight_rule`` mapping (``{}``: the defaults). An option it does not take raises a
        ``ValueError`` naming the options it takes (was a ``TypeError`` the job read as a value of the wrong type)."""
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(options) - set(names), key=str)
        if unknown:
            raise ValueError(f"weight_rule takes {', '.join(names)}; not {', '.join(map(str, unknown))}")
        return cls(**options)

    def target(self, delta2: float) -> float:
        """The data term aimed at for noise ``delta2``: ``tau^2 delta^2``."""
        return self.tau**2 * max(delta2, 0.0)

    def next_weight(self, weight: float, residual: float, delta2: float, may_raise: bool = True) -> float:
        """The weight whose residual should meet the target, from ``residual`` (data term ``D``)
        reached with ``weight``: ``weight (target / D)^(1 / slope)`` in ``[floor, largest]``, or
        ``weight`` itself when ``D`` is within ``tolerance`` of the target; never above ``weight``
        unless ``may_raise`` (``False`` for an estimated noise, see the module docstring)."""
        goal = self.target(delta2)
        if goal <= 0:
            return self.floor
        if residual <= 0:
            return self.largest if may_raise else weight
        if abs(residual / goal - 1) <= self.tolerance:
            return weight
        step = min(max(weight * (goal / residual) ** (1 / self.slope), self.floor), self.largest)
        return step if may_raise else min(step, weight)

    def record(self, weight: float, first_residual: float, residual: float, noise: tuple[float, str]) -> dict:
        """The choice and its reason (for ``Reconstruction.info`` and ``metrics.json``): ``weight``
        chosen after the first solve reached ``first_residual``, ``residual`` the final data term."""
        goal = self.target(noise[0])
        if weight == self.start and goal > 0 and abs(first_residual / goal - 1) <= self.tolerance:
            why = "the first weight's solution already matches tau times the noise"
        elif weight == self.start and first_residual < goal and noise[1] not in KNOWN_NOISE:
            why = ("an estimated noise (which includes the profiles' own curvature) lies above the residual but "
                   "never raises the weight: first weight kept")
        elif weight <= self.floor * (1 + 1e-9) and first_residual > goal:
            why = ("the noise lies below the residual the data allow (noise-free data): floor weight"
                   if noise[1] not in KNOWN_NOISE else  # a known noise: the model misses the data by more
                   f"the residual the data allow lies above their noise (from the {noise[1]}): the model's own "
                   "error (the voxels, the rig geometry) exceeds it: floor weight")
        elif weight >= self.largest * (1 - 1e-9) and first_residual < goal:
            why = "even the largest weight is expected to fit the data more closely than the noise: largest weight"
        else:
            why = "the weight expected to bring the residual to tau times the noise"
        root = math.sqrt
        return {"rule": self.rule, "reason": why, "weight": weight, "tau": self.tau, "start": self.start,
                "noise_residual": root(max(noise[0], 0.0)), "noise_source": noise[1], "target_residual": root(goal),
                "first_residual": root(max(first_residual, 0.0)), "residual_reached": root(max(residual, 0.0))}


def _weight(name: str, options) -> object:
    """The weight entry of one prior's options (a bare number or string is the weight itself)."""
    weight = options if isinstance(options, (int, float, str)) else dict(options).get("weight", 0.0)
    if isinstance(weight, str) and weight != AUTO:
        raise ValueError(f"prior {name!r} has weight {weight!r}: give a number or {AUTO!r}")
    return weight


def auto_names(spec: Mapping[str, Mapping]) -> list[str]:
    """Names of the priors of ``spec`` (``{name: {"weight": w, ...}}``) whose weight is ``"auto"``."""
    return [name for name, options in spec.items() if _weight(name, options) == AUTO]


def prior_options(value) -> dict:
    """One prior's options as a dict: a bare number or ``"auto"`` is its weight."""
    return {"weight": value} if isinstance(value, (int, float, str)) else dict(value)


def with_weight(spec: Mapping[str, Mapping], weight: float) -> dict[str, dict]:
    """``spec`` with every ``"auto"`` weight replaced by ``weight``."""
    out = {}
    for name, options in spec.items():
        auto = _weight(name, options) == AUTO
        options = prior_options(options)
        out[name] = {**options, "weight": weight} if auto else options
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
    if sigma is None:
        sigma, source = torch.full_like(target, estimate_slab_sigma(target)), "estimated"
    else:
        source = "sigma"
    filled = filled_slabs(target, rel_tol)
    return float((weight.double() * sigma.double().pow(2))[filled].sum()), source
