"""One call from a shape to a simulated measurement: dip (physics) then preprocess.

Defaults, for an object of about 100 mm
---------------------------------------
* tank: 300 x 200 mm (free cross-section ``A`` = 60,000 mm^2), 150 mm of water; in 2D a
  300 mm wide slot (``A`` = 300 mm, so areas in mm^2 / 300 mm = level rise in mm);
* sensor: an ideal water-level transducer (no noise, no quantisation; pass
  ``LevelSensor(snr_db=..., quantum_mm=...)`` or ``sigma_mm=...`` for a real one, or a :class:`Balance`);
* protocol: 1 mm steps, starting 3 mm below the object's bounding sphere, 3 extra readings
  once the object is under water, 2 s per step;
* slabs: the operator's slabs of ``grid`` (``[-L/2, L/2]`` in ``n_slabs`` slabs) so the
  measurement lines up with :func:`~dipnet.operators.make_operator` without resampling.

In 2D every volume is an area (mm^2) and the tank cross-section is a width (mm).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from dipnet.core.grid import Grid, as_grid
from dipnet.core.measurement import DipMeasurement
from dipnet.simulator.physics import DipProtocol, SensorModel, Tank, simulate_scan
from dipnet.simulator.pockets import Pockets
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import RawScan
from dipnet.core.geometry import RigGeometry, as_geometry, invert_scan


def simulate_measurement(shape, directions, *, grid: Grid | None = None, n_slabs: int | None = None,
                         edges=None, tank: Tank | None = None, sensor: SensorModel | None = None,
                         step_mm: float | None = None, protocol: DipProtocol | None = None,
                         geometry: RigGeometry | None = None, reader_geometry: RigGeometry | None = None,
                         pockets: Pockets | bool | None = None, smooth: bool = False,
                         t_start: str | float = "metadata", seed: int | None = None,
                         progress: bool = True) -> tuple[RawScan, DipMeasurement]:
    """Simulate dipping ``shape`` along ``directions`` and preprocess the raw scan.

    Args:
        shape: a :class:`~dipnet.shapes.Shape` (2D or 3D); its exact ``volume_below`` is the physics.
        directions: unit "up" vectors ``(K, shape.ndim)``.
        grid, n_slabs: the reconstruction grid; the slabs default to the operator's
            (``n_slabs`` default ``grid.n``).
        edges: explicit uniform slab edges ``(M + 1,)`` mm instead of ``grid``; without either,
            ``n_slabs`` (default 64) slabs over the shape's bounding sphere.
        tank, sensor, protocol: physics settings (defaults in the module docstring).
        step_mm: stage step (mm), overriding ``protocol.step_mm``.
        geometry: the rig's true geometry (or a mapping of its fields), applied by the simulator
            (default: the ideal rig).
        reader_geometry: the geometry preprocessing assumes (:func:`~dipnet.core.geometry.invert_scan`);
            default the ideal (nominal) rig. Equal to ``geometry``, the profiles are the ideal ones.
        pockets: trap air in cavities that open downward and keep those that open upward dry until the
            water reaches their rim (:class:`~dipnet.simulator.pockets.Pockets`; ``True`` its defaults).
            Default: water reaches every cavity at once, as the dip transform assumes.
        smooth: apply the paper's 5-tap Gaussian to the profiles.
        t_start: how preprocessing places the profiles (default: the simulator's known start).
        seed: noise seed (default the sensor's).
        progress: progress bar over orientations.

    Returns:
        ``(raw scan, measurement)``; profiles ``(K, M)`` in mm^3 (mm^2 in 2D).
    """
    protocol = protocol or DipProtocol()
    if step_mm is not None:
        protocol = replace(protocol, step_mm=float(step_mm))
    if grid is not None and as_grid(grid).ndim != shape.ndim:
        raise ValueError(f"the shape is {shape.ndim}D but the grid is {grid.ndim}D")
    if edges is None and grid is None:
        r = float(shape.radius())
        edges = np.linspace(-r, r, (64 if n_slabs is None else int(n_slabs)) + 1)
    raw = simulate_scan(shape, directions, tank=tank, sensor=sensor, protocol=protocol,
                        geometry=as_geometry(geometry), pockets=pockets, seed=seed, progress=progress)
    read = raw if reader_geometry is None else invert_scan(raw, as_geometry(reader_geometry))
    measurement = preprocess(read, edges=edges, grid=grid, n_slabs=n_slabs, smooth=smooth, t_start=t_start)
    return raw, measurement
