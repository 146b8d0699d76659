"""Mesh shapes: loading, exact dips, sealed voids, repair of broken meshes, clear file errors."""

import warnings

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.shapes import Ball, MeshShape, ShapeError, ShapeWarning, from_trimesh, load_mesh

from dipnet.preprocessing.datasets import MESHES_DIR as MESHES

SHARED = sorted(MESHES.glob("*.ply"))


def unit_directions(k: int, seed: int) -> torch.Tensor:
    v = torch.randn(k, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return v / v.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("path", SHARED, ids=lambda p: p.stem)
def test_shared_meshes_volume_and_dips(path):
    expected = trimesh.load(path).volume
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShapeWarning)  # hollow_cube: void filled (tested below)
        shape = load_mesh(path)
    if path.stem != "hollow_cube":
        assert shape.notes == []
        assert shape.volume == pytest.approx(expected, rel=1e-9)
    r = shape.radius()
    v = shape.volume_below(unit_directions(20, 0), torch.linspace(-1.01 * r, 1.01 * r, 80))
    assert (v[:, 0] == 0).all()
    torch.testing.assert_close(v[:, -1], torch.full((20,), shape.volume, dtype=torch.float64))
    assert (v.diff(dim=1) >= -1e-9 * shape.volume).all()


@pytest.mark.parametrize("stem", ["bunny", "spot", "torus"])
def test_shared_mesh_occupancy_matches_volume(stem):
    grid = Grid(40, 3, 100.0)
    shape = load_mesh(MESHES / f"{stem}.ply", radius=0.9 * grid.radius)
    assert shape.radius() == pytest.approx(0.9 * grid.radius)
    assert np.allclose(shape.mesh.center_mass, 0, atol=1e-9 * grid.extent)
    occ = shape.occupancy(grid, supersample=2)
    assert occ.sum().item() * grid.voxel_volume == pytest.approx(shape.volume, rel=0.03)


def test_hollow_cube_sealed_void_is_filled_by_default():
    with pytest.warns(ShapeWarning, match="filled 1 sealed"):
        filled = load_mesh(MESHES / "hollow_cube.ply")
    assert filled.volume == pytest.approx(8.0) and any("sealed" in n for n in filled.notes)
    with pytest.warns(ShapeWarning, match="kept 1 sealed"):
        kept = load_mesh(MESHES / "hollow_cube.ply", fill_sealed_voids=False)
    assert kept.volume == pytest.approx(7.0)
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    h = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64)
    torch.testing.assert_close(filled.volume_below(up, h)[0], 4 * (h + 1))
    void_below = h.clamp(-0.5, 0.5) + 0.5
    torch.testing.assert_close(kept.volume_below(up, h)[0], 4 * (h + 1) - void_below)
    grid = Grid(16, 3, 2.5)
    centre = (slice(6, 10),) * 3  # voxels inside the cavity [-0.5, 0.5]^3
    assert (filled.occupancy(grid)[centre] == 1).all() and (kept.occupancy(grid)[centre] == 0).all()


def test_nested_shells_outer_void_island():
    """Shells nested three deep: solid, sealed void, solid island inside the void."""
    boxes = [trimesh.creation.box(extents=[e] * 3) for e in (4.0, 2.0, 1.0)]
    boxes[1].invert()  # written as a void, like a CAD export would
    mesh = trimesh.util.concatenate(boxes)
    with pytest.warns(ShapeWarning):
        assert from_trimesh(mesh).volume == pytest.approx(64.0)
    with pytest.warns(ShapeWarning):
        assert from_trimesh(mesh, fill_sealed_voids=False).volume == pytest.approx(64 - 8 + 1)


def test_overlapping_shells_are_merged():
    a = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    b = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    b.apply_translation([1.0, 0.5, 0.0])  # overlap volume 1 * 1.5 * 2 = 3
    with pytest.warns(ShapeWarning, match="merged 2 overlapping"):
        shape = from_trimesh(trimesh.util.concatenate([a, b]))
    assert shape.volume == pytest.approx(16.0 - 3.0)
    # scaled, the overlap is named in the file's units (it said "3 mm^3" as if in mm) and as a share
    with pytest.warns(ShapeWarning, match=r"overlap 3 mm\^3 in the file's units, 18.8% of the shells' volume"):
        from_trimesh(trimesh.util.concatenate([a, b]), scale=10.0)


def block_with(piece: str) -> tuple[trimesh.Trimesh, float]:
    """A 40 x 40 x 20 mm block (z -10..10) and a second closed piece that touches it, is pressed into it or
    sticks out of it, saved as two shells of one mesh; returns the mesh and its union's exact volume (mm^3)."""
    block = trimesh.creation.box(extents=[40.0, 40.0, 20.0])
    if piece == "stacked box":  # 20 mm box standing on the top face
        other = trimesh.creation.box(extents=[20.0, 20.0, 20.0]).apply_translation([0.0, 0.0, 20.0])
        union = 32000.0 + 8000.0
    elif piece == "half-sunk box":  # 20 mm box, its lower half inside the block
        other = trimesh.creation.box(extents=[20.0, 20.0, 20.0]).apply_translation([0.0, 0.0, 10.0])
        union = 32000.0 + 4000.0
    elif piece == "pin":  # radius 5 mm, 3 mm inside the block, 60 mm sticking out (vertices only at its ends)
        other = trimesh.creation.cylinder(radius=5.0, height=63.0).apply_translation([0.0, 0.0, 7.0 + 31.5])
        union = 32000.0 + 0.5 * 32 * 5.0**2 * np.sin(2 * np.pi / 32) * 60.0  # the 32-gon prism outside
    else:  # "side sphere": centred on the side face x = 20; the icosphere is symmetric, so half of it sticks out
        other = trimesh.creation.icosphere(subdivisions=3, radius=10.0).apply_translation([20.0, 0.0, 0.0])
        union = 32000.0 + other.volume / 2
    return trimesh.util.concatenate([block, other]), union


@pytest.mark.parametrize("fill", [True, False], ids=["filled", "kept"])
@pytest.mark.parametrize("piece", ["stacked box", "half-sunk box", "pin", "side sphere"])
def test_touching_or_protruding_pieces_are_solid_not_sealed_voids(piece, fill):
    """Before: a piece whose probe vertices mostly lay inside the block was taken for a sealed void and dropped
    (32000 mm^3 instead of 40000 for the stacked boxes, the pin lost entirely), or with fill_sealed_voids=False
    cut out as a void (the stacked boxes: 24000 mm^3, refused as a failed repair). A piece that is not wholly
    inside another is solid: the shape is their union, in its volume, its dips and its occupancy."""
    mesh, union = block_with(piece)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always", ShapeWarning)
        shape = from_trimesh(mesh, center=False, fill_sealed_voids=fill)
    assert not any("sealed" in str(w.message) for w in record)
    assert shape.volume == pytest.approx(union, rel=1e-9)
    assert shape.bounds()[1][2] == pytest.approx(mesh.bounds[1][2])
    out = torch.tensor([[1.0, 0.0, 0.0] if piece == "side sphere" else [0.0, 0.0, 1.0]], dtype=torch.float64)
    heights = torch.tensor([20.0 if piece == "side sphere" else 10.0, 100.0], dtype=torch.float64)
    below, total = shape.volume_below(out, heights)[0].tolist()
    assert total == pytest.approx(union, rel=1e-9)  # the dips hold the union, the overlap once
    assert total - below == pytest.approx(union - 32000.0, abs=1e-9 * union)  # beyond the block's face: its part
    grid = Grid(32, 3, 140.0)
    merged = MeshShape(trimesh.boolean.union(mesh.split(), engine="manifold"))  # one closed surface
    assert merged.volume == pytest.approx(union, rel=1e-9)
    torch.testing.assert_close(shape.occupancy(grid, supersample=2), merged.occupancy(grid, supersample=2))


def test_a_bar_whose_vertices_all_lie_in_a_notched_block_is_not_a_void():
    """A block with a 10 mm wide, 5 mm deep notch across its top, and a bar bridging the notch: every corner of
    the bar lies in the block's walls, but its middle crosses the notch. Only points on the bar's faces show
    it is not wholly inside; before, its vertices' vote dropped it as a sealed void (30000 mm^3, not 30080)."""
    block = trimesh.creation.box(extents=[40.0, 40.0, 20.0])
    notch = trimesh.creation.box(extents=[10.0, 60.0, 10.0]).apply_translation([0.0, 0.0, 10.0])
    notched = trimesh.boolean.difference([block, notch], engine="manifold")
    bar = trimesh.creation.box(extents=[30.0, 4.0, 4.0]).apply_translation([0.0, 0.0, 5.0])  # z 3..7, notch z 5..10
    assert MeshShape(notched).contains(bar.vertices).all()
    with pytest.warns(ShapeWarning, match="merged 2 overlapping"):
        shape = from_trimesh(trimesh.util.concatenate([notched, bar]), center=False)
    assert shape.volume == pytest.approx(32000.0 - 10 * 40 * 5 + 10 * 4 * 2, rel=1e-9)


@pytest.mark.parametrize("inner_inverted", [True, False], ids=["inverted", "same-oriented"])
def test_hollow_ball_and_island_stay_nested(inner_inverted):
    """A ball of radius 20 mm with a cavity of radius 10 mm and an island of radius 5 mm in the cavity: the
    inner shells lie wholly inside the outer one, so they stay a sealed void (filled by default) and an
    island, however the inner sphere is oriented."""
    outer, cavity, island = (trimesh.creation.icosphere(subdivisions=3, radius=r) for r in (20.0, 10.0, 5.0))
    if inner_inverted:
        cavity.invert()
    volumes = [abs(m.volume) for m in (outer, cavity, island)]
    with pytest.warns(ShapeWarning, match="filled 1 sealed inner void"):
        assert from_trimesh(trimesh.util.concatenate([outer, cavity])).volume == pytest.approx(volumes[0])
    with pytest.warns(ShapeWarning) as record:  # and, for the same-oriented cavity, "inverted 1 of 3 shells"
        kept = from_trimesh(trimesh.util.concatenate([outer, cavity, island]), fill_sealed_voids=False)
    assert any("kept 1 sealed inner void" in str(w.message) for w in record)
    assert kept.volume == pytest.approx(volumes[0] - volumes[1] + volumes[2])


def broken_icosphere(extra_hole: bool) -> trimesh.Trimesh:
    """An icosphere with 5 deleted faces, one flipped face and, optionally, a pentagonal hole."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rng = np.random.default_rng(0)
    faces = np.delete(m.faces, rng.choice(len(m.faces), 5, replace=False), axis=0)
    faces[10] = faces[10][::-1]
    if extra_hole:
        faces = faces[~np.any(faces == 0, axis=1)]
    return trimesh.Trimesh(m.vertices, faces, process=False)


@pytest.mark.parametrize("extra_hole", [False, True])
def test_broken_mesh_loads_with_warning_and_sensible_occupancy(tmp_path, extra_hole):
    path = tmp_path / "broken.stl"
    broken_icosphere(extra_hole).export(path)
    with pytest.warns(ShapeWarning, match="broken.stl") as record:
        shape = load_mesh(path, radius=40.0)
    message = str(record[0].message)
    assert "flipped" in message and "not watertight" in message
    assert shape.exact == (not extra_hole)  # tri holes are filled, the pentagon stays open
    if extra_hole:
        assert "approximate" in message
    grid = Grid(32, 3, 100.0)
    occ = shape.occupancy(grid, supersample=2)
    ball = Ball(40.0).occupancy(grid, supersample=2)
    assert (occ - ball).abs().sum() / ball.sum() < 0.03
    assert shape.volume == pytest.approx(Ball(40.0).volume, rel=0.02)


@pytest.mark.parametrize("suffix", ["stl", "obj", "off", "ply", "glb"])
def test_formats_round_trip(tmp_path, suffix):
    m = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    path = tmp_path / f"ball.{suffix}"
    m.export(path)
    shape = load_mesh(path, center=False)
    assert isinstance(shape, MeshShape) and shape.name == "ball"
    assert shape.volume == pytest.approx(m.volume, rel=1e-6)


def test_glb_scene_is_concatenated(tmp_path):
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    ball = trimesh.creation.icosphere(subdivisions=2, radius=1.0).apply_translation([4.0, 0, 0])
    path = tmp_path / "scene.glb"
    trimesh.Scene([box, ball]).export(path)
    assert load_mesh(path).volume == pytest.approx(box.volume + ball.volume, rel=1e-6)


def test_physical_size_is_kept_without_radius(tmp_path):
    m = trimesh.creation.box(extents=[10.0, 20.0, 30.0]).apply_translation([5.0, 5.0, 5.0])
    path = tmp_path / "brick.stl"
    m.export(path)
    shape = load_mesh(path)
    assert shape.volume == pytest.approx(6000.0)
    assert shape.radius() == pytest.approx(np.linalg.norm([5.0, 10.0, 15.0]))


@pytest.mark.parametrize("size", [{"scale": 0.0}, {"scale": -1.0}, {"scale": float("nan")}, {"scale": float("inf")},
                                  {"scale": 1e-300}, {"radius": float("inf")}, {"radius": 1e-300}],
                         ids=["scale0", "mirror", "scale-nan", "scale-inf", "scale-tiny", "radius-inf", "radius-tiny"])
def test_a_scale_or_radius_that_is_no_size_is_refused(tmp_path, size):
    """Before: load_mesh(path, scale=0) gave a shape of volume 0 and radius 0, scale=-1 the mirror image (the
    same volume, no word), scale=nan or inf a shape of volume NaN (the torus: a segmentation fault)."""
    path = tmp_path / "brick.stl"
    trimesh.creation.box(extents=[10.0, 20.0, 30.0]).export(path)
    with pytest.raises(ShapeError, match="brick.stl: .*(finite, positive|outside \\[1e-12, 1e\\+12\\] mm)"):
        load_mesh(path, **size)
    assert load_mesh(path, scale=2.0).volume == pytest.approx(48000.0)


def test_file_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.stl"
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00not a mesh\xff" * 20)
    empty = tmp_path / "empty.ply"
    empty.write_text("")
    flat = tmp_path / "flat.obj"
    plane = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]])
    plane.export(flat)
    for path in (missing, garbage, empty, flat):
        with pytest.raises(ShapeError, match=path.name):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ShapeWarning)
                load_mesh(path)
    with pytest.raises(ShapeError, match="is a directory, not a mesh file"):
        load_mesh(tmp_path)
    for blank in ("", " "):  # shape.path= left empty: it read as "mesh path . is a directory"
        with pytest.raises(ShapeError, match=r"no mesh file given: set its path \(shape.path="):
            load_mesh(blank)


def test_a_hole_bent_over_an_edge_is_refused_and_a_flat_one_filled():
    """A 40 x 30 x 20 box without the two triangles that meet at one of its 40 mm edges: its square hole is
    bent over that edge, and the two ways to fill it enclose 24000 or 20000 mm^3; their difference, the
    hull of the rim (40 x 30 x 20 / 6 = 4000 mm^3, 20 % of the filled box), is named and refused. Without
    one triangle the rim is flat, every fill is the same, and the box keeps its 24000 mm^3."""
    box = trimesh.creation.box(extents=[40.0, 30.0, 20.0])
    edge = np.array(box.face_adjacency_edges)[~np.isclose(box.face_adjacency_angles, 0.0)]
    long_edge = next(e for e in edge if abs(np.ptp(box.vertices[e][:, 0])) == 40.0)
    pair = [i for i, f in enumerate(box.faces) if set(long_edge) <= set(f)]
    bent = trimesh.Trimesh(box.vertices, np.delete(box.faces, pair, axis=0), process=False)
    with pytest.raises(ShapeError, match=r"holes' rims leave 20.0% of its volume uncertain \(more than 5%"):
        from_trimesh(bent, name="bent")
    flat = trimesh.Trimesh(box.vertices, np.delete(box.faces, pair[:1], axis=0), process=False)
    with pytest.warns(ShapeWarning, match="filled small holes") as record:
        shape = from_trimesh(flat, name="flat")
    assert "uncertain" not in str(record[0].message)
    assert shape.volume == pytest.approx(24000.0, rel=1e-9)


def test_a_sealed_void_is_named_in_mm3_once_scaled():
    """A cube of side 2 (file units) with a sealed cavity of side 1, scaled to 45 mm: its void was named "1 mm^3"
    (the file's units), where it holds 17,537 mm^3, 12.5 % of the solid."""
    outer = trimesh.creation.box((2.0, 2.0, 2.0))
    cavity = trimesh.creation.box((1.0, 1.0, 1.0))
    cavity.invert()
    with pytest.warns(ShapeWarning, match=r"filled 1 sealed inner void\(s\) of total volume 17537 mm\^3, 12.5% of "
                                          r"the solid"):
        from_trimesh(trimesh.util.concatenate([outer, cavity]), radius=45.0)
    with pytest.warns(ShapeWarning, match=r"kept 1 sealed inner void\(s\) of total volume 1000 mm\^3, 14.3% of"):
        from_trimesh(trimesh.util.concatenate([outer, cavity]), scale=10.0, fill_sealed_voids=False)


def test_the_shape_remembers_its_scale_so_points_map_back_to_the_file(tmp_path):
    """``frame_scale`` is the mm per unit of the file: ``(p + frame_offset) / frame_scale`` is a grid-frame point
    ``p`` in the file's own coordinates, for a radius, a scale and neither."""
    source = trimesh.creation.box(extents=(30.0, 20.0, 10.0)).apply_translation([40.0, -25.0, 12.0])
    source.export(tmp_path / "box.stl")
    for options, factor in (({}, 1.0), ({"scale": 1000.0}, 1000.0),
                            ({"radius": 45.0}, 45.0 / np.linalg.norm([15.0, 10.0, 5.0]))):
        shape = load_mesh(tmp_path / "box.stl", **options)
        assert shape.frame_scale == pytest.approx(factor), options
        lo, hi = ((b + shape.frame_offset) / shape.frame_scale for b in shape.bounds())
        np.testing.assert_allclose(np.stack([lo, hi]), source.bounds, atol=1e-9, err_msg=str(options))


@pytest.mark.parametrize("module, message", [
    ("lxml", r"tet.3mf: reading a .3mf file needs the Python module lxml, which is not installed: pip install lxml"),
    ("charset_normalizer", r"tet.3mf: corrupt, or not a mesh format trimesh reads"),
])
def test_a_format_whose_reader_module_is_missing_names_the_module(tmp_path, monkeypatch, module, message):
    """Before: a valid .3mf without lxml installed was "corrupt, or not a mesh format trimesh reads" (every
    ImportError was taken for trimesh's text fallback on unparsable binary, which needs a charset detector)."""
    def load(*args, **kwargs):
        raise ModuleNotFoundError(f"No module named '{module}'")

    path = tmp_path / "tet.3mf"
    path.write_bytes(b"PK")
    monkeypatch.setattr(trimesh, "load", load)
    with pytest.raises(ShapeError, match=message):
        load_mesh(path)


def test_a_scale_beside_a_radius_is_refused_by_the_api_as_by_shape_from_file():
    """Before: ``load_mesh(path, radius=45, scale=1000)`` took the radius and dropped the scale without a word."""
    with pytest.raises(ShapeError, match=r"torus.ply: radius=45 and scale=1000 both set the mesh's size"):
        load_mesh(MESHES / "torus.ply", radius=45.0, scale=1000.0)
    assert load_mesh(MESHES / "torus.ply", radius=45.0, scale=1.0).radius() == pytest.approx(45.0)
