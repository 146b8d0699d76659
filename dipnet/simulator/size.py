"""Size check of the dip simulator before it allocates.

The dip simulator's size (:func:`dipnet.simulator.physics.simulate_scan`) follows from the object,
not the grid: one reading per stage step across the object's bounding sphere,
``n = (2 R + clearance) / step``, so a mesh in the wrong units (a 3e7 mm "sphere") asks for 60
million readings per dip. It refuses more than :data:`MAX_READINGS_PER_DIP` readings per dip (100 m
of travel at 1 mm steps: no rig dips that deep) or more memory than is available: one dip's solver
arrays (``n`` times :meth:`~dipnet.shapes.Shape.dip_bytes_per_reading`) plus the raw scan it keeps
(stage, value and time of every reading, ``24 K n``).
"""

from __future__ import annotations

from dipnet.core.memory import MAX_READINGS_PER_DIP, MemoryEstimate, ResourceError, available_memory, format_bytes
from dipnet.shapes.base import Shape


def check_simulation(shape, n_dips: int, readings_per_dip: int, step_mm: float,
                     available: int | None = None) -> MemoryEstimate:
    """Raise :class:`ResourceError` when simulating ``n_dips`` dips of ``readings_per_dip``
    readings (stage steps of ``step_mm`` mm) of ``shape`` takes more than
    :data:`MAX_READINGS_PER_DIP` readings per dip or more than ``available`` bytes (default:
    :func:`available_memory`); returns the estimate. The message gives the object's size, the
    readings and the fix (the object's units, or a coarser step)."""
    k, n = int(n_dips), int(readings_per_dip)
    per_reading = getattr(shape, "dip_bytes_per_reading", None)  # duck-typed shapes: the Shape default
    per_reading = float(per_reading()) if per_reading is not None else Shape.dip_bytes_per_reading(shape)
    estimate = MemoryEstimate({"dip solver": n * per_reading, "raw scan": 24.0 * k * n})
    available = available_memory() if available is None else available
    too_long = n > MAX_READINGS_PER_DIP
    if too_long or (available is not None and estimate.total > available):
        limit = (f"at most {MAX_READINGS_PER_DIP:,} per dip" if too_long
                 else f"this machine has {format_bytes(available)} available")
        raise ResourceError(
            f"the simulator would take {n:,} readings per dip ({k} dips: {k * n:,} readings, needing "
            f"{estimate.describe()}; {limit}) for an object of radius {shape.radius():.4g} mm at {step_mm:g} mm "
            "steps: is the object in mm? Give its size with shape.radius= (mm) or its units with shape.scale= "
            "(mm per file unit), or a coarser source.simulator.protocol.step_mm=")
    return estimate

