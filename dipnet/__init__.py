"""dipnet: 3D shape reconstruction from dip transform (fluid displacement) measurements.

A small scripting API (see README.md and docs/getting-started.md)::

    import dipnet
    grid = dipnet.Grid(40, ndim=3, extent=100.0)                 # 40^3 voxels over 100 mm
    dirs = dipnet.fibonacci_hemisphere(60)                        # (K, 3) dip directions
    op = dipnet.make_operator(grid, dirs)                         # forward / adjoint
    shape = dipnet.builtin_shape("chamber_box", 3, 0.9 * grid.radius)
    raw, meas = dipnet.simulate_measurement(shape, dirs, grid=grid)
    dipnet.validate_measurement(meas, grid)                       # refuses wrong units, NaN, too small a grid, ...
    recon = dipnet.make_solver("minnorm").solve(meas, op)
    check = dipnet.check_consistency(meas, op, recon)             # does recon explain the dips?
"""

from dipnet.jobs import resolvers  # noqa: F401 (registers the ${dipnet_data:...} config resolver)
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement, MeasurementFileError
from dipnet.operators import BACKENDS, DipOperator, make_operator
from dipnet.core.orientations import (angles_2d, directions_2d, fibonacci_hemisphere, make_directions, paper_grid,
                                      random_hemisphere, rig_to_direction)
from dipnet.simulator.physics import Balance, DipProtocol, LevelSensor, Tank
from dipnet.preprocessing.preprocess import preprocess, preprocess_file
from dipnet.core.rawscan import RawScan, read_rawscan
from dipnet.core.rawscan_writer import RawScanWriter
from dipnet.core.reconstruction import Reconstruction
from dipnet.shapes import Shape, ShapeError, builtin_shape, load_mesh, shape_from_file
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers import SOLVERS, Solver, make_solver
from dipnet.preprocessing.validation import MeasurementValidationError, validate_measurement
from dipnet.evaluation.consistency import Consistency, DataConsistencyWarning, check_consistency

__version__ = "0.1.0"

__all__ = [
    "BACKENDS", "Balance", "Consistency", "DataConsistencyWarning", "DipMeasurement", "DipOperator", "DipProtocol",
    "Grid", "LevelSensor", "MeasurementFileError", "MeasurementValidationError", "RawScan", "RawScanWriter",
    "Reconstruction", "SOLVERS", "Shape", "ShapeError", "Solver", "Tank", "angles_2d", "builtin_shape",
    "check_consistency", "directions_2d", "fibonacci_hemisphere", "load_mesh", "make_directions", "make_operator",
    "make_solver", "paper_grid", "preprocess", "preprocess_file", "random_hemisphere", "read_rawscan",
    "rig_to_direction", "shape_from_file", "simulate_measurement", "validate_measurement",
]
