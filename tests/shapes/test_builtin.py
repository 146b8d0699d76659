"""Built-in shapes: every name in 2D and 3D, at the asked size in mm; unknown names and sizes refused."""

import pytest

from dipnet.preprocessing.datasets import mesh_path
from dipnet.shapes import ShapeError
from dipnet.shapes.builtin import builtin_names, builtin_shape, shape_from_file


@pytest.mark.parametrize("ndim", [2, 3])
def test_every_builtin_has_the_asked_radius(ndim):
    for name in builtin_names(ndim):
        shape = builtin_shape(name, ndim, 25.0)
        assert shape.radius() == pytest.approx(25.0, rel=1e-6), name
        assert 0 < shape.volume < (2 * 25.0) ** ndim, name  # inside its bounding cube


def test_names_dimensions_and_sizes_are_checked():
    assert {"ball", "torus", "chamber_box"} <= set(builtin_names(3)) and "disk" in builtin_names(2)
    with pytest.raises(ShapeError, match="unknown built-in 3D shape 'disk'"):
        builtin_shape("disk", 3, 10.0)
    with pytest.raises(ShapeError, match="radius must be a finite, positive number"):
        builtin_shape("ball", 3, 0.0)
    with pytest.raises(ShapeError, match="not 4D"):
        builtin_names(4)


def test_a_mesh_file_at_a_radius_and_its_silhouette():
    solid = shape_from_file(str(mesh_path("bunny")), 3, radius=30.0)
    assert solid.radius() == pytest.approx(30.0, rel=1e-6)
    flat = shape_from_file(str(mesh_path("bunny")), 2, radius=30.0)
    assert flat.ndim == 2 and flat.radius() <= 30.0 + 1e-6
    with pytest.raises(ShapeError, match="scale must be positive"):
        shape_from_file(str(mesh_path("bunny")), 3, scale=0.0)


def test_a_mesh_file_refuses_a_scale_beside_a_radius_and_an_unknown_axis():
    """Before: ``shape.radius=30 shape.scale=1000`` ignored the scale without a word, and ``shape.axis=q`` was
    accepted in 3D (refused only by the first 2D run)."""
    with pytest.raises(ShapeError, match=r"shape.radius=30 and shape.scale=1000 both set the mesh's size"):
        shape_from_file(str(mesh_path("bunny")), 3, radius=30.0, scale=1000.0)
    with pytest.raises(ShapeError, match=r"shape.axis must be 'x', 'y' or 'z' .*, got 'q'"):
        shape_from_file(str(mesh_path("bunny")), 3, radius=30.0, axis="q")
    assert shape_from_file(str(mesh_path("bunny")), 3, scale=1000.0).radius() > 1000.0  # a scale alone still scales
