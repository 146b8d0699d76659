"""Shapes: meshes, analytic solids and 2D silhouettes with exact dips and voxel occupancy.

Every shape follows :class:`~dipnet.shapes.base.Shape`: ``occupancy(grid, supersample)``,
``volume_below(directions, heights)`` (exact, from the true geometry), ``volume`` and ``radius()``.
"""

from dipnet.shapes.analytic import Ball, Box, ChamberBox, Disk, Torus
from dipnet.shapes.base import Shape, ShapeError, ShapeWarning
from dipnet.shapes.builtin import DEFAULT_SHAPE, builtin_names, builtin_shape, shape_from_file
from dipnet.shapes.divergence import boundary_volume_below
from dipnet.shapes.mesh import MeshShape, from_trimesh, load_mesh
from dipnet.shapes.silhouettes import PolygonShape, elephant, project_mesh

__all__ = [
    "Ball",
    "Box",
    "ChamberBox",
    "DEFAULT_SHAPE",
    "Disk",
    "MeshShape",
    "PolygonShape",
    "Shape",
    "ShapeError",
    "ShapeWarning",
    "Torus",
    "boundary_volume_below",
    "builtin_names",
    "builtin_shape",
    "elephant",
    "from_trimesh",
    "load_mesh",
    "project_mesh",
    "shape_from_file",
]
