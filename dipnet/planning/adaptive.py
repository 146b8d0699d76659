"""The closed planning loop: dip, reconstruct, measure the doubt, plan the next batch, repeat.

:func:`adaptive_loop` is the loop itself, independent of where dips come from: the simulator
(:class:`dipnet.simulator.source.SimulatedDips`, driven by :class:`dipnet.planning.plans.AdaptivePlan`
behind ``planner=adaptive`` in ``scripts/reconstruct.py``) and the rig (:mod:`dipnet.rig.adaptive`)
give it an ``acquire`` callback. It starts from
``initial_dips`` directions spread uniformly over the reachable set, and after each
reconstruction either stops - at the ``budget`` of dips, when the expected misclassified
fraction (:func:`dipnet.evaluation.uncertainty.summarise`) falls below ``stop_uncertainty``, or when every
candidate direction of the reach is measured (``"candidates"``: a dip along a measured direction measures the
same planes again, minutes of robot time for nothing new; a warning says so and how to get more candidates) - or
asks the planner for the next ``batch_size`` reachable directions that are not measured yet (fewer when fewer are
left).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from dipnet.core.counts import is_real
from dipnet.core.measurement import DipMeasurement
from dipnet.core.warn import log_and_warn
from dipnet.operators import DipOperator
from dipnet.core.orientations import Reach
from dipnet.planning.planner import MEASURED_DEG, Planner, repeated_directions, unmeasured_lines
from dipnet.core.rawscan import RawScan, RawScanFileError
from dipnet.core.reconstruction import Reconstruction
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.evaluation.uncertainty import summarise, voxel_maps

log = logging.getLogger(__name__)

Acquire = Callable[[torch.Tensor], DipMeasurement]
Reconstruct = Callable[[DipMeasurement], tuple[Reconstruction, DipOperator]]


@dataclass(frozen=True)
class AdaptiveSettings:
    """How the loop runs.

    Attributes:
        budget: the most dips in all.
        batch_size: dips planned per step.
        initial_dips: dips spread uniformly over the reach before the first plan.
        stop_uncertainty: stop early when ``expected_error_fraction`` drops below this, a fraction in (0, 1)
            (``None``: never); a percentage (5 for 5 %) would stop after the first dips, so 1 and above are refused.
    """

    budget: int = 41
    batch_size: int = 8
    initial_dips: int = 8
    stop_uncertainty: float | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.initial_dips <= self.budget or self.batch_size < 1:
            raise ValueError(f"need 1 <= initial_dips <= budget and batch_size >= 1, got initial_dips "
                             f"{self.initial_dips}, budget {self.budget}, batch_size {self.batch_size}")
        if self.initial_dips == self.budget:
            log_and_warn(log, f"planner=adaptive with initial_dips = budget = {self.budget}: every dip is spread "
                              "evenly over the reach before the first plan, so none is planned from the data (the "
                              "run is planner=fixed's with those dips): lower planner.initial_dips or raise "
                              "planner.budget", stacklevel=3)
        stop = self.stop_uncertainty
        if stop is not None and not is_real(stop):  # true read as 1
            raise ValueError(f"stop_uncertainty must be a fraction in (0, 1) or null (the share of the object's "
                             f"volume expected misclassified, e.g. 0.05), got {stop!r}")
        if stop is not None:
            object.__setattr__(self, "stop_uncertainty", float(stop))
        if self.stop_uncertainty is not None and not 0 < self.stop_uncertainty < 1:
            hint = (f" ({self.stop_uncertainty:g} would stop after the first {self.initial_dips} dips, whatever the "
                    f"budget; for {self.stop_uncertainty:g} % give {self.stop_uncertainty / 100:g})"
                    if self.stop_uncertainty >= 1 else "")
            raise ValueError(f"stop_uncertainty must be a fraction in (0, 1) or null (the share of the object's "
                             f"volume expected misclassified, e.g. 0.05), got {self.stop_uncertainty:g}{hint}")


@dataclass
class AdaptiveResult:
    """What the loop ended with: the last measurement and reconstruction, its uncertainty maps
    (:func:`dipnet.evaluation.uncertainty.voxel_maps`), one history row per step and why it stopped
    (``"budget"``, ``"uncertainty"`` or ``"candidates"``: every candidate direction of the reach measured)."""

    measurement: DipMeasurement
    reconstruction: Reconstruction
    operator: DipOperator
    maps: dict[str, np.ndarray]
    history: list[dict[str, Any]] = field(default_factory=list)
    stop_reason: str = "budget"


def adaptive_loop(acquire: Acquire, reconstruct: Reconstruct, planner: Planner, reach: Reach,
                  settings: AdaptiveSettings, initial: torch.Tensor | None = None) -> AdaptiveResult:
    """Run the loop (module docstring).

    Args:
        acquire: dips the new directions ``(k, 3)`` and returns the measurement of *all* dips so far.
        reconstruct: measurement -> (reconstruction, its operator).
        planner: chooses the next directions among ``reach.candidates()``.
        reach: what the rig reaches.
        settings: budget, batch size, initial dips, stopping threshold.
        initial: the first directions (default ``reach.uniform(settings.initial_dips)``).
    """
    planned = reach.uniform(settings.initial_dips) if initial is None else torch.as_tensor(initial, dtype=torch.float64)
    repeated = repeated_directions(planned)
    if repeated.any():  # the loop never dips a measured direction again, the initial dips included
        _warn_repeated_initial(int(repeated.sum()), len(planned), reach)
        planned = planned[torch.from_numpy(~repeated)]
    candidates = reach.candidates()
    history: list[dict[str, Any]] = []
    while True:
        measurement = acquire(planned)
        recon, operator = reconstruct(measurement)
        posterior = planner.posterior(recon, measurement, operator)  # fitted once: reported and planned with
        maps = voxel_maps(recon, posterior)
        summary = summarise(maps, recon.binary)
        n = measurement.n_orientations
        # the grid and slabs the posterior was fitted on: at most the reconstruction's, coarser with many dips
        history.append({"n_dips": n, **summary, "posterior_resolution": posterior.grid.n,
                        "posterior_slabs": posterior.n_slabs})
        log.info("adaptive step: %d dips, expected error fraction %.4f", n, summary["expected_error_fraction"])
        if n >= settings.budget:
            return AdaptiveResult(measurement, recon, operator, maps, history, "budget")
        if settings.stop_uncertainty is not None and summary["expected_error_fraction"] < settings.stop_uncertainty:
            return AdaptiveResult(measurement, recon, operator, maps, history, "uncertainty")
        wanted = min(settings.batch_size, settings.budget - n)
        left = unmeasured_lines(candidates, measurement.directions)
        if left < wanted:
            _warn_few_candidates(left, wanted, n, len(candidates), settings.budget, reach)
            if not left:
                return AdaptiveResult(measurement, recon, operator, maps, history, "candidates")
        start = time.perf_counter()
        planned = planner.next(measurement, recon, candidates, min(wanted, left), operator, posterior=posterior)
        history[-1]["plan_seconds"] = time.perf_counter() - start


def _warn_few_candidates(left: int, wanted: int, n_dips: int, n_candidates: int, budget: int, reach: Reach) -> None:
    """Warn that only ``left`` of the reach's ``n_candidates`` directions are not measured after ``n_dips`` dips, fewer
    than the ``wanted`` next batch: the loop plans ``left`` (and stops when 0 are left) short of ``budget``."""
    then = f"the loop stops at {n_dips} dips" if not left else f"the loop plans those {left}"
    message = (f"planner=adaptive: after {n_dips} dips only {left} of the reach's {n_candidates} candidate directions "
               f"are not measured yet (within {MEASURED_DEG:g} deg), fewer than the {wanted} of the next batch: "
               f"{then}, "
               f"short of the budget of {budget} (a dip along a measured direction measures the same planes again); "
               f"for more candidates give a finer reach.step_deg (now {reach.step_deg:g} deg) or a wider reach "
               f"(tilt {reach.tilt_range_deg[0]:g}-{reach.tilt_range_deg[1]:g} deg)")
    log_and_warn(log, message, stacklevel=3)


def _warn_repeated_initial(repeated: int, planned: int, reach: Reach) -> None:
    """Warn that ``repeated`` of the ``planned`` initial directions repeat an earlier one (within
    :data:`~dipnet.planning.planner.MEASURED_DEG`), so the loop starts from the others alone."""
    message = (f"planner=adaptive: {repeated} of the {planned} initial dips spread over the reach ({reach.ranges()}) "
               f"repeat an earlier direction (within {MEASURED_DEG:g} deg), which "
               f"measures the same planes again: the loop starts from the other {planned - repeated}; a wider reach "
               f"gives more directions")
    log_and_warn(log, message, stacklevel=3)


def warn_linear_loop_solver(solver) -> None:
    """Warn when the loop reconstructs with ``minnorm``: the planner takes its noise level from the
    estimate's misfit, which for a min-norm estimate is model error (120x the sensor noise on the
    bunny after 16 dips), and every candidate then scores about the same."""
    if isinstance(solver, MinNormSolver):  # lsqr, lsmr too: solver=lsqr was named solver=minnorm
        name = getattr(solver, "name", "minnorm")
        message = (f"planner=adaptive with solver={name}: the planner's noise level comes from the estimate's "
                   f"misfit, which for {name} (a min-norm estimate) is model error, so the candidates score alike; "
                   "use solver=voxel")
        log_and_warn(log, message, stacklevel=2)


def keep_recorded(recorded: RawScan, planned: list[tuple[float, float]], first: int, reach: Reach | None,
                  path: Path) -> list[tuple[float, float]]:
    """``planned`` ``(tilt_deg, spin_deg)`` angles of dips ``first, first + 1, ...`` with every dip
    that ``recorded`` started put back at its recorded angles (module docstring): a warning per
    step that differs; :class:`RawScanFileError` for a recorded dip outside ``reach``."""
    out, moved = list(planned), []
    for o in recorded.orientations:
        i = o.k - first
        if 0 <= i < len(out) and not np.allclose((o.tilt_deg, o.spin_deg), out[i], atol=1e-6):
            direction = torch.as_tensor(o.unit_direction, dtype=torch.float64)[None]
            if reach is not None and not bool(reach.contains(direction)[0]):
                raise RawScanFileError(f"{path}: dip {o.k} was recorded at (tilt, spin) = "
                                       f"({o.tilt_deg}, {o.spin_deg}), "
                                       f"outside the rig's reach now ({reach}): the config changed; use another "
                                       f"scan name")
            moved.append(f"dip {o.k}: recorded ({o.tilt_deg:g}, {o.spin_deg:g}), replayed plan ({out[i][0]:g}, "
                         f"{out[i][1]:g})")
            out[i] = (float(o.tilt_deg), float(o.spin_deg))
    if moved:
        message = (f"{path}: the replayed plan differs from the recorded dips ({'; '.join(moved)}); the recorded "
                   f"dips are kept and planning goes on from them (a different thread count or library version "
                   f"changes floating-point sums, or the planner's config changed)")
        log_and_warn(log, message, stacklevel=2)
    return out
