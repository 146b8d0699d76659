"""``solver=voxel``: one logit per voxel, annealed toward a binary occupancy.

The occupancy is ``o = sigmoid(z / T) * mask`` with parameters ``z`` (one per voxel) and a
temperature ``T`` that falls geometrically from ``temperature_start`` to ``temperature_end``
over the run, so the solution is soft (easy to optimise) early and nearly binary at the end.
Voxels outside the working ball, and outside the data's support hull (see
:func:`~dipnet.solvers.optimize.support_hull`), are fixed at 0. With ``coarse_to_fine`` the first
``coarse_fraction`` of the steps solve on a grid of half the resolution (same directions and
slabs, so the same measured profiles), whose logits are then upsampled to start the full grid.

Defaults (chosen with ``scripts/bench_quality.py`` at 64^3 on the shared meshes): Adam, lr 0.1,
cosine schedule, 400 steps (30% at 32^3), temperature 1 -> 0.25, isotropic TV with its weight
chosen from the noise (``"auto"``, :mod:`dipnet.solvers.weights`: 1e-3 for the first solve, then
a refit at the chosen weight; a number fixes it). Binarising harder (``temperature_end`` << 0.25)
loses the partial-volume sub-voxel surface that the Chamfer distance rewards.

``rounds`` repeats the whole solve, each round warm-started from the last one's occupancy, with its
priors built afresh. With the learned prior in ``anchor`` mode this is plug-and-play half-quadratic
splitting: each round fits the data under a pull toward ``D`` of the previous round's result
(``solver=voxel_learned``, docs/guide/solvers.md, "Learned prior"). Every round pulls the result
further toward the prior, so with ``rounds_tau`` a round after the first runs only while the last
result's data term is at most ``rounds_tau^2 delta^2`` (``delta^2``: the noise's own data term from
the measurement's sigma, :func:`~dipnet.solvers.weights.noise_level`): Morozov's discrepancy
principle, the most regularised result that still explains the data to within their noise. A noise
*estimated* from the profiles (no sigma given) includes the profiles' own curvature, so, as with the
TV weight rule (:mod:`dipnet.solvers.weights`), it never licenses a stronger prior: no round beyond ``min_rounds``.

``later_priors`` changes the priors of the rounds after the first (merged over ``priors``, prior by
prior), and ``min_rounds`` rounds run whatever the rule says. ``solver=voxel_learned`` uses both for
its cascade: round 1 anchors to ``D1`` (trained on plain voxel results), round 2 always runs and
anchors to ``D2`` (trained on round-1 results, the artifacts it meets there), and rounds 3-6 keep
``D2`` while the discrepancy rule allows.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.counts import is_real, whole_number
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import DipOperator, backend_name, make_operator
from dipnet.core.keywords import forwards_to
from dipnet.core.reconstruction import Reconstruction
from dipnet.core.flags import checked_flag
from dipnet.solvers.base import checked_temperatures, on_operator_slabs
from dipnet.solvers.optimize import OptimisationSolver, merge_histories, plain, seeded
from dipnet.solvers.priors import build_priors, checked_priors
from dipnet.solvers.weights import KNOWN_NOISE, prior_options, with_weight

_CLIP = 0.02  # initial occupancies are clipped to [_CLIP, 1 - _CLIP] before taking logits
MIN_COARSE_N = 8


def _resample(volume: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """Area-average down or (bi/tri)linearly up to ``shape``."""
    if tuple(volume.shape) == tuple(shape):
        return volume
    mode = "area" if volume.shape[-1] > shape[-1] else ("bilinear" if volume.ndim == 2 else "trilinear")
    extra = {} if mode == "area" else {"align_corners": False}
    return F.interpolate(volume[None, None], size=shape, mode=mode, **extra)[0, 0]


class VoxelSolver(OptimisationSolver):
    """Per-voxel logits with temperature annealing and optional coarse-to-fine.

    Args:
        temperature_start, temperature_end: sigmoid temperature at the first and last step
            (geometric in between); ``temperature_end < temperature_start`` anneals toward binary.
        coarse_to_fine: start on a half-resolution grid (when ``N // 2 >= 8``).
        coarse_fraction: share of ``iterations`` spent on the coarse grid.
        rounds: solves in a row, each warm-started from the last (see the module docstring).
        rounds_tau: stop the rounds after the first whose data term exceeds ``rounds_tau^2`` times the
            noise's (see the module docstring); ``None``: every round runs.
        min_rounds: rounds that run whatever ``rounds_tau`` says (at most ``rounds``).
        later_priors: ``{name: options}`` merged over ``priors`` (per prior) for rounds 2 and on,
            e.g. ``{"learned": {"weights": "denoiser64_stage2"}}``; ``None``: every round the same.
        **options: :class:`~dipnet.solvers.optimize.OptimisationSolver` options
            (iterations, lr, optimizer, schedule, tol, window, priors, warm_start, seed,
            threshold, progress).
    """

    name = "voxel"

    @forwards_to(OptimisationSolver)
    def __init__(self, temperature_start: float = 1.0, temperature_end: float = 0.25, coarse_to_fine: bool = True,
                 coarse_fraction: float = 0.3, rounds: int = 1, rounds_tau: float | None = None,
                 min_rounds: int = 1, later_priors: Mapping[str, Mapping] | None = None, **options) -> None:
        options.setdefault("iterations", 400)
        options.setdefault("lr", 0.1)
        options.setdefault("priors", {"tv": {"weight": "auto"}, "binary": {"weight": 0.0},
                                      "volume": {"weight": 0.0}})
        super().__init__(**options)
        temperature_start, temperature_end = checked_temperatures(temperature_start, temperature_end)
        if not is_real(coarse_fraction) or not 0 <= coarse_fraction < 1:
            raise ValueError(f"coarse_fraction must be in [0, 1), got {coarse_fraction!r}")
        rounds, min_rounds = whole_number("rounds", rounds, low=1), whole_number("min_rounds", min_rounds, low=1)
        if rounds_tau is not None and (not is_real(rounds_tau) or not 0 < rounds_tau < math.inf):
            raise ValueError(f"rounds_tau must be a positive, finite number or null (the data term's limit, in noise "
                             f"units), got {rounds_tau!r}")
        if not 1 <= int(min_rounds) <= int(rounds):
            raise ValueError(f"min_rounds must be in [1, rounds={rounds}], got {min_rounds!r}")
        self.min_rounds = int(min_rounds)
        later_priors = checked_priors("later_priors", later_priors)
        self.later_priors = None if later_priors is None else self._merged(plain(later_priors))
        if self.later_priors is not None:
            build_priors(with_weight(self.later_priors, self.weight_rule.start), volume_fraction=1.0)  # validate now
        self.temperature_start, self.temperature_end = float(temperature_start), float(temperature_end)
        self.coarse_to_fine, self.coarse_fraction = (checked_flag("coarse_to_fine", coarse_to_fine),
                                                     float(coarse_fraction))
        self.rounds, self.rounds_tau = int(rounds), None if rounds_tau is None else float(rounds_tau)

    def _merged(self, later: Mapping[str, Mapping]) -> dict[str, dict]:
        """:attr:`priors` with each prior's options updated by ``later``'s (a bare number is a weight)."""
        merged = {name: prior_options(value) for name, value in self.priors.items()}
        for name, value in later.items():
            merged[name] = {**merged.get(name, {}), **prior_options(value)}
        return merged

    def prior_specs(self) -> list[Mapping[str, Mapping]]:
        """:attr:`priors` and, when set, :attr:`later_priors` (rounds 2 and on)."""
        return [self.priors] + ([self.later_priors] if self.later_priors is not None else [])

    def temperature(self, fraction: float) -> float:
        """Temperature after ``fraction`` (0..1) of the whole run."""
        return self.temperature_start * (self.temperature_end / self.temperature_start) ** fraction

    def _stages(self, operator: DipOperator) -> list[tuple[DipOperator, int, float, float]]:
        """``(operator, iterations, start fraction, end fraction)`` per stage."""
        grid = operator.grid
        if not self.coarse_to_fine or grid.n // 2 < MIN_COARSE_N or self.coarse_fraction == 0:
            return [(operator, self.iterations, 0.0, 1.0)]
        coarse = make_operator(Grid(grid.n // 2, grid.ndim, grid.extent), operator.directions, operator.n_slabs,
                               backend=backend_name(operator), **getattr(operator, "options", {}))
        n_coarse = max(1, round(self.coarse_fraction * self.iterations))
        c = n_coarse / self.iterations
        return [(coarse, n_coarse, 0.0, c), (operator, max(1, self.iterations - n_coarse), c, 1.0)]

    def solve(self, measurement: DipMeasurement, operator: DipOperator) -> Reconstruction:
        """Reconstruct on ``operator.grid``; ``history`` holds the loss terms of every stage of every
        round in order, ``info`` the stages' rounds, resolutions and steps and the final temperature."""
        started = time.perf_counter()
        measurement = on_operator_slabs(measurement, operator)  # resampled (and warned about) once
        start = self._initial_occupancy(measurement, operator)
        histories, stage_info, rounds = [], [], {}
        for k in range(1, self.rounds + 1):
            label = "" if self.rounds == 1 else f" round {k}/{self.rounds}"
            priors = self.later_priors if k > 1 and self.later_priors is not None else self.priors
            occ, history, stages, last = self._round(measurement, operator, start, label, priors)
            histories.append(history)
            noise = last.pop("noise")
            if self.rounds > 1:  # each round's stages with its final data term
                residual = history["data"][-1]
                stages = [{"round": k, **stage, "data": residual} for stage in stages]
                rounds = self._rounds_record(k, residual, noise)
            stage_info += stages
            start = occ
            if rounds.get("stopped"):
                break
        recon = self._result(occ, operator, merge_histories(*histories), started, stages=stage_info, **last,
                             **({"rounds": rounds} if rounds else {}))
        return self._refit_surface(recon, measurement, operator)

    def _rounds_record(self, done: int, residual: float, noise: tuple[float, str]) -> dict:
        """``info["rounds"]`` after round ``done`` with data term ``residual``: rounds run and allowed,
        the discrepancy test (see ``rounds_tau``) and whether it stops the rounds here."""
        record = {"done": done, "max": self.rounds, "rule": "fixed" if self.rounds_tau is None else "discrepancy",
                  "residual": residual ** 0.5, "noise_residual": max(noise[0], 0.0) ** 0.5, "noise_source": noise[1]}
        if self.rounds_tau is None:
            return record
        goal = self.rounds_tau**2 * max(noise[0], 0.0)
        known, within = noise[1] in KNOWN_NOISE, residual <= goal
        if done < self.min_rounds:
            reason = f"the first min_rounds={self.min_rounds} rounds always run"
        elif not known:
            reason = ("the noise is estimated from the profiles (an upper bound that includes their own curvature), "
                      "which never licenses a stronger prior: no further round")
        elif not within:
            reason = ("the data term exceeds rounds_tau^2 x the noise's: a further round would pull the result off "
                      "its data")
        else:
            reason = "the data term stays within rounds_tau^2 x the noise's"
        stopped = self.min_rounds <= done < self.rounds and not (known and within)
        return {**record, "tau": self.rounds_tau, "target_residual": goal**0.5, "stopped": stopped, "reason": reason}

    def _round(self, measurement: DipMeasurement, operator: DipOperator, init: torch.Tensor | None,
               label: str, priors: Mapping[str, Mapping]) -> tuple[torch.Tensor, dict, list[dict], dict]:
        """One solve from ``init`` (``None``: uniform) under the priors ``priors`` (options, as
        :attr:`priors`): ``(occupancy, history, stages, info)``, ``info`` holding the data term,
        priors, weight record, final temperature and support size."""
        logits: torch.Tensor | None = None  # u = z / T, carried between stages
        histories, stage_info = [], []
        with seeded(self.seed):
            for op, steps, f0, f1 in self._stages(operator):  # a gain is fitted on the full grid only (see fit_gain)
                problem = self._problem(measurement, op, self.fit_gain and op is operator, priors)
                data, built, fraction, support = problem.data, problem.priors, problem.volume_fraction, problem.support
                mask = support.to(torch.float32)
                if logits is None:
                    room = float(mask.mean())  # share of the cube that may be filled
                    start = init if init is not None else torch.full(op.grid.shape, min(fraction / room, 1.0))
                    start = _resample(start, op.grid.shape).clamp(_CLIP, 1 - _CLIP)
                    logits = torch.logit(start)
                else:
                    logits = _resample(logits, op.grid.shape)
                temp = {"T": self.temperature(f0)}
                z = nn.Parameter(logits * temp["T"])

                def anneal(p: float, temp=temp, f0=f0, f1=f1) -> None:
                    temp["T"] = self.temperature(f0 + p * (f1 - f0))

                def occupancy(z=z, mask=mask, temp=temp) -> torch.Tensor:
                    return torch.sigmoid(z / temp["T"]) * mask

                desc = f"voxel {op.grid.n}^{op.grid.ndim}{label}"
                histories.append(self._loop([z], occupancy, data, built, steps, desc, before_step=anneal))
                logits = (z.detach() / temp["T"])
                stage_info.append({"n": op.grid.n, "steps": len(histories[-1]["loss"])})
            # "auto" weights: chosen from the full grid's residual, then refitted at the final temperature
            refit, used, weights = self.choose_weights(problem, [z], occupancy, steps, desc)
            if refit:
                histories.append(refit)
                logits = z.detach() / temp["T"]
        occ = torch.sigmoid(logits) * mask
        info = {"data": data, "priors": used, "weights": weights, "final_temperature": temp["T"],
                "support_voxels": int(mask.sum()), "noise": problem.noise}
        return occ, merge_histories(*histories), stage_info, info
