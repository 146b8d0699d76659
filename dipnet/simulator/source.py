"""The simulated measurement source (``source=simulated``): dips of a known shape, simulated along a plan.

:class:`SimulatedSource` has the methods of every source (the recorded one is
:class:`dipnet.preprocessing.sources.RecordedSource`): :meth:`~SimulatedSource.truth`,
:meth:`~SimulatedSource.extent_mm`, :meth:`~SimulatedSource.measure` (a finished measurement and
its raw scan) and :meth:`~SimulatedSource.record` (the raw scan for self-calibration).
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import Callable

import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import Reach
from dipnet.core.rawscan import RawScan
from dipnet.preprocessing.recorded import finish_measurement
from dipnet.preprocessing.sources import Acquisition, Recording, finish_dips
from dipnet.preprocessing.validation import MeasurementValidationError
from dipnet.shapes import Shape

Simulate = Callable[..., tuple[RawScan, DipMeasurement]]


def concatenate(first: DipMeasurement, second: DipMeasurement) -> DipMeasurement:
    """The dips of ``first`` followed by those of ``second`` (same slabs), as one measurement."""
    if first.n_slabs != second.n_slabs or abs(first.slab_thickness - second.slab_thickness) > 1e-9:
        raise ValueError("measurements to concatenate must share the slab count and thickness")
    sigma = None
    if first.sigma is not None and second.sigma is not None:
        sigma = torch.cat([first.sigma, second.sigma])
    return DipMeasurement(torch.cat([first.directions, second.directions]),
                          torch.cat([first.profiles, second.profiles]),
                          first.slab_thickness, torch.cat([first.offsets, second.offsets]), sigma, dict(first.metadata))


def merge_raw(first: RawScan, second: RawScan) -> RawScan:
    """The orientations of ``second`` appended to ``first``'s, renumbered after them."""
    offset = len(first.orientations)
    return replace(first, orientations=first.orientations + [replace(o, k=o.k + offset) for o in second.orientations])


def simulated_drifts(keywords: dict, raw: RawScan | None) -> str:
    """The drifts configured for the simulator (``keywords``: the sensor's ``drift_mm_per_s`` or ``drift_g_per_s``,
    the geometry's ``level_drift_mm_per_s``), each named by its option with what it adds over the longest dip of
    ``raw``; ``""`` without one."""
    span = max((float(o.time_s[-1] - o.time_s[0]) for o in (raw.orientations if raw else []) if len(o.time_s) > 1),
               default=0.0)
    sensor, geometry = keywords.get("sensor"), keywords.get("geometry")
    found = []
    for option, owner, name in (("source.simulator.sensor", sensor, "drift_mm_per_s"),
                                ("source.simulator.sensor", sensor, "drift_g_per_s"),
                                ("source.simulator.geometry", geometry, "level_drift_mm_per_s")):
        rate = owner.get(name) if isinstance(owner, dict) else getattr(owner, name, None)
        if rate:
            unit = "g" if name.startswith("drift_g") else "mm"
            found.append(f"{option}.{name}={rate:g} ({unit}/s; {rate * span:.3g} {unit} over a dip of {span:.0f} s)")
    return " and ".join(found)


class SimulatedDips:
    """A plan's ``acquire`` for simulated dips: simulates the new directions and returns the
    measurement of all dips so far (:attr:`measurement`; their raw scan in :attr:`raw`).

    Args:
        simulate: :func:`dipnet.simulator.simulate.simulate_measurement` or a partial of it.
        shape, grid, n_slabs: what is dipped and the reconstruction slabs.
        seed: noise seed; each batch gets its own stream (``seed + 7919 * dips so far``).
    """

    def __init__(self, simulate: Simulate, shape, grid: Grid, n_slabs: int, seed: int, progress: bool = False) -> None:
        self.simulate, self.shape, self.grid, self.n_slabs = simulate, shape, grid, n_slabs
        self.seed, self.progress = seed, progress
        self.raw: RawScan | None = None
        self.measurement: DipMeasurement | None = None

    def __call__(self, directions: torch.Tensor) -> DipMeasurement:
        done = 0 if self.measurement is None else self.measurement.n_orientations
        raw, new = self.simulate(self.shape, directions, grid=self.grid, n_slabs=self.n_slabs,
                                 seed=self.seed + 7919 * done, progress=self.progress)
        self.raw = raw if self.raw is None else merge_raw(self.raw, raw)
        self.measurement = new if self.measurement is None else concatenate(self.measurement, new)
        return self.measurement


class SimulatedSource:
    """Dips simulated from the shape's own geometry along a plan's directions.

    Args:
        simulator: :func:`dipnet.simulator.simulate.simulate_measurement` with its physics bound
            (tank, sensor, protocol, rig geometry, smoothing), called as
            ``simulator(shape, directions, grid=, n_slabs=, seed=, progress=)``.
    """

    def __init__(self, simulator: Simulate) -> None:
        self.simulator = simulator

    def truth(self, configured: Callable[[], Shape], build: Callable[[dict], Shape] | None = None) -> Shape:
        """The object the dips are scored against: the configured shape (``configured()``; ``build`` is
        for sources that name their own shape)."""
        return configured()

    def extent_mm(self) -> float | None:
        """No grid side of its own: the grid is chosen around the shape."""
        return None

    def _dip(self, plan, grid: Grid, n_slabs: int, shape: Shape, seed: int, progress: bool, reach: Reach | None,
             solver, make_operator):
        if shape.radius() > grid.radius * (1 + 1e-6):
            raise ValueError(f"shape {shape.name!r} (radius {shape.radius():.1f} mm) does not fit the working "
                             f"ball of radius {grid.radius:.1f} mm: increase extent_mm (or leave it null)")
        dips = SimulatedDips(self.simulator, shape, grid, n_slabs, seed, progress)
        result = plan.run(dips, grid.ndim, reach, solver, make_operator)
        return dips.raw, result

    def measure(self, plan, grid: Grid, n_slabs: int, *, shape: Shape, seed: int = 0, progress: bool = True,
                reach: Reach | None = None, solver=None, make_operator=None, symmetry=None) -> Acquisition:
        """Dip ``shape`` along ``plan`` (:mod:`dipnet.planning.plans`; ``solver`` and ``make_operator``
        for a plan that reconstructs as it goes), then check and symmetrise the measurement
        (:func:`dipnet.preprocessing.sources.finish_dips`)."""
        raw, result = self._dip(plan, grid, n_slabs, shape, seed, progress, reach, solver, make_operator)
        try:
            measurement, validation = finish_dips(result.measurement, grid, symmetry)
        except MeasurementValidationError as err:
            drifts = simulated_drifts(getattr(self.simulator, "keywords", {}), raw)
            if not drifts:
                raise
            raise MeasurementValidationError(f"{err}; but the likely cause is the simulated drift: {drifts}, "
                                             "which the dips read as the object's volume: lower it (0: none)") from err
        return Acquisition(measurement, validation, raw, result.report)

    def record(self, plan, grid: Grid, n_slabs: int, *, shape: Shape, seed: int = 0, progress: bool = True,
               reach: Reach | None = None, solver=None, make_operator=None, symmetry=None) -> Recording:
        """The raw scan of :meth:`measure`'s dips for self-calibration, with how to finish every trial
        measurement (symmetry) and whether the simulator smooths."""
        raw, _ = self._dip(plan, grid, n_slabs, shape, seed, progress, reach, solver, make_operator)
        keywords = getattr(self.simulator, "keywords", {})
        finish = partial(finish_measurement, symmetry=symmetry) if symmetry else None
        return Recording(raw, smooth=bool(keywords.get("smooth", False)), finish=finish, new=True)
