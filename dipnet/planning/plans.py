"""Dip plans: which directions a source is dipped along (config group ``planner``).

A plan drives an ``acquire`` callback (directions ``(k, d)`` in, the measurement of every dip so
far out; e.g. :class:`dipnet.simulator.source.SimulatedDips`):

* :class:`FixedPlan` (``planner=fixed``): ``n_dips`` directions of an orientation set, planned up
  front and kept within the rig's reach;
* :class:`AdaptivePlan` (``planner=adaptive``): the closed loop of :func:`dipnet.planning.adaptive.adaptive_loop`.

Both return a :class:`PlanResult`: the final measurement and, for the loop, its report.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable

import torch

from dipnet.core.counts import whole_number
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import Reach, make_directions
from dipnet.core.warn import log_and_warn
from dipnet.operators import DipOperator
from dipnet.planning.adaptive import Acquire, AdaptiveSettings, adaptive_loop, warn_linear_loop_solver
from dipnet.planning.planner import MEASURED_DEG, NextBestDipPlanner, Planner, repeated_directions
from dipnet.solvers.surface_refit import without_surface_refit

log = logging.getLogger(__name__)

#: directions ``(K, 3)`` -> the operator of a measurement along them
MakeOperator = Callable[[torch.Tensor], DipOperator]


@dataclass
class PlanResult:
    """What a plan ended with: the measurement of all its dips, and the loop's report
    (``{"stop_reason", "history", "posterior"}``: why it stopped, one row per step, how the posterior behind the
    rows' uncertainty figures was fitted, its options; each row's ``posterior_resolution`` and ``posterior_slabs``
    are the grid and slabs it was fitted on, at most the reconstruction's grid and coarser with many dips;
    ``None`` for a plan made up front)."""

    measurement: DipMeasurement
    report: dict[str, Any] | None = None


class FixedPlan:
    """Every dip planned up front: ``n_dips`` directions of ``orientations``.

    Args:
        orientations: ``"fibonacci"`` | ``"random"`` | ``"uniform"`` (:func:`dipnet.core.orientations.make_directions`).
        n_dips: the number of dips ``K``, a whole number >= 1.
        seed: seed of ``"random"``, a whole number >= 0.

    Raises:
        ValueError: naming ``n_dips`` or ``seed`` when it is not a whole number in range (``planner.n_dips=8.5``
            was cut to 8 dips, ``planner.seed=1.5`` to seed 1, unsaid).
    """

    def __init__(self, orientations: str = "fibonacci", n_dips: int = 120, seed: int = 0) -> None:
        self.orientations, self.n_dips, self.seed = (str(orientations), whole_number("n_dips", n_dips, low=1),
                                                     whole_number("seed", seed, low=0))  # 8.5 was cut to 8 dips

    def directions(self, ndim: int, reach: Reach | None = None) -> torch.Tensor:
        """The planned unit directions ``(K, ndim)``, kept within ``reach`` (3D): a Fibonacci or
        uniform plan that leaves it becomes the uniform plan over the reach (a warning when the reach is too narrow
        for ``K`` distinct directions); a random one is refused."""
        directions = make_directions(self.orientations, self.n_dips, ndim, self.seed)
        if ndim == 2 or reach is None or bool(reach.contains(directions).all()):
            return directions
        if self.orientations in ("fibonacci", "uniform"):
            directions = reach.uniform(self.n_dips)
            repeated = int(repeated_directions(directions).sum())
            if repeated:
                message = (f"n_dips={self.n_dips} over the reach ({reach.ranges()}): {repeated} of the dips repeat "
                           f"an earlier direction "
                           f"(within {MEASURED_DEG:g} deg) and measure the same planes again, "
                           f"{self.n_dips - repeated} distinct direction(s) in all; a wider reach gives more")
                log_and_warn(log, message, stacklevel=2)
            return directions
        raise ValueError(f"orientations={self.orientations} leaves the reach (tilt {reach.tilt_range_deg}, spin "
                         f"{reach.spin_range_deg} deg): use orientations=fibonacci or another reach")

    def run(self, acquire: Acquire, ndim: int, reach: Reach | None, solver=None,
            make_operator: MakeOperator | None = None) -> PlanResult:
        """Dip every planned direction at once (``solver`` and ``make_operator`` are not needed)."""
        return PlanResult(acquire(self.directions(ndim, reach)))


class AdaptivePlan:
    """The closed loop: ``initial_dips`` spread over the reach, then batches of ``batch_size`` chosen by
    ``planner`` until ``budget`` dips or an expected misclassified fraction below ``stop_uncertainty``
    (:class:`~dipnet.planning.adaptive.AdaptiveSettings`)."""

    def __init__(self, budget: int = 41, batch_size: int = 8, initial_dips: int = 8,
                 stop_uncertainty: float | None = None, planner: Planner | None = None) -> None:
        budget, batch_size = whole_number("budget", budget), whole_number("batch_size", batch_size)
        initial_dips = whole_number("initial_dips", initial_dips)
        try:
            self.settings = AdaptiveSettings(budget=budget, batch_size=batch_size, initial_dips=initial_dips,
                                             stop_uncertainty=stop_uncertainty)
        except ValueError as exc:  # opened with the option at fault, which a job's error names by its path
            if str(exc).startswith("need "):
                raise ValueError(f"{'batch_size' if batch_size < 1 else 'initial_dips'}: {exc}") from None
            raise
        self.planner = planner or NextBestDipPlanner()

    def run(self, acquire: Acquire, ndim: int, reach: Reach | None, solver=None,
            make_operator: MakeOperator | None = None) -> PlanResult:
        """Run the loop, reconstructing with ``solver`` on the operators of ``make_operator`` (3D only;
        ``reach`` default: the hemisphere)."""
        if ndim != 3:
            raise ValueError(f"planner=adaptive plans 3D dips; got ndim={ndim} (use planner=fixed)")
        if solver is None or make_operator is None:
            raise ValueError("the adaptive loop reconstructs after every batch: give solver and make_operator")
        warn_linear_loop_solver(solver)
        loop_solver = without_surface_refit(solver)  # the loop reads occupancies; the job refits its own result

        def reconstruct(measurement: DipMeasurement):
            operator = make_operator(measurement.directions)
            return loop_solver.solve(measurement, operator), operator

        result = adaptive_loop(acquire, reconstruct, self.planner, reach or Reach(), self.settings)
        return PlanResult(result.measurement, {"stop_reason": result.stop_reason, "history": result.history,
                                               "posterior": self.planner.posterior_settings()})
