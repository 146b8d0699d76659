"""dipnet: 3D shape reconstruction from dip transform (fluid displacement) measurements.

A small scripting API (see README, "Python API")::

    import dipnet
    grid = dipnet.Grid(32, ndim=3, extent=100.0)                 # 32^3 voxels over 100 mm
    dirs = dipnet.fibonacci_hemisphere(100)                       # (K, 3) dip directions
    op = dipnet.make_operator(grid, dirs)                         # forward / adjoint
    shape = dipnet.builtin_shape("chamber_box", 3, 0.9 * grid.radius)
    raw, meas = dipnet.simulate_measurement(shape, dirs, grid=grid)
    recon = dipnet.make_solver("minnorm").solve(meas, op)
"""

from dipnet import datasets  # registers the ${dipnet_data:...} config resolver
from dipnet.grid import Grid
from dipnet.measurement import DipMeasurement, MeasurementFileError
from dipnet.operators import BACKENDS, DipOperator, make_operator
from dipnet.orientations import (angles_2d, directions_2d, fibonacci_hemisphere, make_directions, paper_grid,
                                 random_hemisphere, rig_to_direction)
from dipnet.physics import Balance, DipProtocol, LevelSensor, Tank
from dipnet.preprocess import preprocess, preprocess_file
from dipnet.rawscan import RawScan, RawScanWriter, read_rawscan
from dipnet.reconstruction import Reconstruction
from dipnet.shapes import Shape, ShapeError, builtin_shape, load_mesh, shape_from_file
from dipnet.simulate import simulate_measurement
from dipnet.solvers import SOLVERS, Solver, make_solver

__version__ = "0.1.0"

__all__ = [
    "BACKENDS", "Balance", "DipMeasurement", "DipOperator", "DipProtocol", "Grid", "LevelSensor",
    "MeasurementFileError", "RawScan", "RawScanWriter", "Reconstruction", "SOLVERS", "Shape", "ShapeError",
    "Solver", "Tank", "angles_2d", "builtin_shape", "directions_2d", "fibonacci_hemisphere", "load_mesh",
    "make_directions", "make_operator", "make_solver", "paper_grid", "preprocess", "preprocess_file",
    "random_hemisphere", "read_rawscan", "rig_to_direction", "shape_from_file", "simulate_measurement",
]
