"""The dips a reconstruct job takes: the config's fixed plan, or the adaptive loop on the simulator."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import Reach, make_directions
from dipnet.core.reconstruction import Reconstruction
from dipnet.operators import DipOperator
from dipnet.planning.adaptive import AdaptiveSettings, SimulatedDips, adaptive_loop, warn_linear_loop_solver


def adaptive_settings(planner_cfg) -> AdaptiveSettings:
    """The loop settings of a ``conf/planner/adaptive.yaml`` node."""
    stop = planner_cfg.get("stop_uncertainty")
    return AdaptiveSettings(budget=int(planner_cfg.budget), batch_size=int(planner_cfg.batch_size),
                            initial_dips=int(planner_cfg.initial_dips),
                            stop_uncertainty=None if stop is None else float(stop))


def fixed_directions(cfg, ndim: int) -> torch.Tensor:
    """The up-front plan of ``planner=fixed``: ``cfg.orientations`` with ``cfg.n_dips`` dips, kept
    within ``cfg.reach`` (a Fibonacci / uniform plan becomes the uniform plan over the reach)."""
    from hydra.utils import instantiate

    directions = make_directions(cfg.orientations, cfg.n_dips, ndim, cfg.seed)
    if ndim == 2 or cfg.get("reach") is None:
        return directions
    reach: Reach = instantiate(cfg.reach)
    if bool(reach.contains(directions).all()):
        return directions
    if cfg.orientations in ("fibonacci", "uniform"):
        return reach.uniform(int(cfg.n_dips))
    raise ValueError(f"orientations={cfg.orientations} leaves the reach (tilt {reach.tilt_range_deg}, spin "
                     f"{reach.spin_range_deg} deg): use orientations=fibonacci or another reach")


def simulate_adaptive(cfg, grid: Grid, shape, out: Path) -> DipMeasurement:
    """``planner=adaptive`` for simulated sources: run the loop with the config's simulator,
    operator, solver, reach and planner; writes ``rawscan.jsonl`` (all dips) and
    ``planning.json`` (history, stop reason) into ``out``; returns the final measurement."""
    from hydra.utils import instantiate

    if grid.ndim != 3:
        raise ValueError(f"planner=adaptive plans 3D dips; got ndim={grid.ndim} (use planner=fixed)")
    n_slabs = cfg.n_slabs or grid.n
    acquire = SimulatedDips(instantiate(cfg.source.simulator), shape, grid, n_slabs, int(cfg.seed),
                            progress=bool(cfg.output.progress))

    solver = instantiate(cfg.solver)
    warn_linear_loop_solver(solver)

    def reconstruct(measurement: DipMeasurement) -> tuple[Reconstruction, DipOperator]:
        operator = instantiate(cfg.operator)(grid, measurement.directions, n_slabs)
        return solver.solve(measurement, operator), operator

    result = adaptive_loop(acquire, reconstruct, instantiate(cfg.planner.planner), instantiate(cfg.reach),
                           adaptive_settings(cfg.planner))
    acquire.raw.save(out / "rawscan.jsonl")
    (out / "planning.json").write_text(json.dumps({"stop_reason": result.stop_reason, "history": result.history},
                                                  indent=2))
    return result.measurement
