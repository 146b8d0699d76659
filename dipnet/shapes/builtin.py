"""Built-in shapes that need no files, scaled to a given radius.

``chamber_box`` is the default in 2D and 3D: a box with an inner chamber reached only through a
narrow channel. Water fills the chamber, so dips measure it, while no camera can see it, which
is the point of the dip transform.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dipnet.shapes.analytic import Ball, Box, ChamberBox, Disk, Torus
from dipnet.shapes.base import Shape, ShapeError, check_radius
from dipnet.shapes.mesh import load_mesh
from dipnet.shapes.silhouettes import elephant, project_mesh

DEFAULT_SHAPE = "chamber_box"


def _chamber_box(ndim: int, radius: float) -> ChamberBox:
    a = radius / np.sqrt(ndim)  # a cube / square whose corners are at `radius`
    return ChamberBox([a] * ndim, chamber_half_sizes=0.5 * a, channel_half_width=0.15 * a)


def _box(radius: float) -> Box:
    ratios = np.array([1.0, 0.7, 0.5])
    return Box(ratios * radius / np.linalg.norm(ratios))


_REGISTRY: dict[int, dict[str, Callable[[float], Shape]]] = {
    3: {
        "chamber_box": lambda r: _chamber_box(3, r),
        "ball": lambda r: Ball(r),
        "box": _box,
        "torus": lambda r: Torus(0.65 * r, 0.35 * r),
    },
    2: {
        "chamber_box": lambda r: _chamber_box(2, r),
        "disk": lambda r: Disk(r),
        "elephant": elephant,
    },
}


def builtin_names(ndim: int) -> list[str]:
    """Names of the built-in shapes of dimension ``ndim`` (2 or 3)."""
    if ndim not in _REGISTRY:
        raise ShapeError(f"built-in shapes exist in 2D and 3D, not {ndim!r}D")
    return list(_REGISTRY[ndim])


def builtin_shape(name: str, ndim: int, radius: float) -> Shape:
    """A built-in shape centred on the origin whose farthest point is ``radius`` mm away.

    Args:
        name: one of :func:`builtin_names` (3D: chamber_box, ball, box, torus;
            2D: chamber_box, disk, elephant).
        ndim: 2 or 3.
        radius: mm, e.g. ``0.9 * grid.radius``.
    """
    names = builtin_names(ndim)
    if name not in names:
        raise ShapeError(f"unknown built-in {ndim}D shape {name!r}; choose one of {names}")
    return _REGISTRY[ndim][name](check_radius(radius))


def shape_from_file(path: str, ndim: int, radius: float | None = None, fill_sealed_voids: bool = True,
                    axis: str = "z", scale: float = 1.0) -> Shape:
    """A mesh file as a 3D shape, or (``ndim=2``) its silhouette projected along ``axis``.

    Args:
        path: any mesh file trimesh reads (PLY, STL, OBJ, OFF, GLB).
        ndim: 3 for the solid, 2 for its projection.
        radius: scale so the farthest point is ``radius`` mm from the centroid (None: keep the
            file's units times ``scale``).
        scale: mm per file unit when ``radius`` is None (e.g. 1000 for a mesh in metres).
        fill_sealed_voids: treat sealed inner voids as solid (water cannot reach them).
        axis: projection axis for 2D (``"x"``, ``"y"`` or ``"z"``; checked in 3D too, where a slip would
            otherwise wait for the first 2D run).

    Raises:
        ShapeError: a scale that is not positive, a scale beside a radius (the radius sets the size, and the
            scale would be ignored without a word), or an axis that is not ``"x"``, ``"y"`` or ``"z"``.
    """
    if radius is not None:
        check_radius(radius)
    if radius is None and not scale > 0:
        raise ShapeError(f"shape scale must be positive (mm per file unit), got {scale!r}")
    if radius is not None and scale != 1.0:
        raise ShapeError(f"shape.radius={radius:g} and shape.scale={scale:g} both set the mesh's size, and with a "
                         f"radius the scale is ignored: give one (shape.radius=null to take the file's units times "
                         f"{scale:g})")
    if axis not in ("x", "y", "z"):
        raise ShapeError(f"shape.axis must be 'x', 'y' or 'z' (the 2D projection's axis), got {axis!r}")
    shape = load_mesh(path, radius=radius, fill_sealed_voids=fill_sealed_voids, scale=None if radius else scale)
    if ndim == 3:
        return shape
    if ndim != 2:
        raise ShapeError(f"shapes exist in 2D and 3D, not {ndim!r}D")
    return project_mesh(shape, axis=axis)  # a projection never lies farther out than the solid
