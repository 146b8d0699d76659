"""Triangle meshes as shapes: loading, cheap repair, sealed voids, inside test, exact dips.

* Inside test: the generalized winding number (libigl ``fast_winding_number``) >= 0.5, which
  stays sensible on meshes with holes, loose shells and flipped faces.
* ``volume_below``: closed form from the triangles by the divergence theorem
  (:mod:`dipnet.shapes.divergence`); exact for a watertight mesh.
* Sealed voids: a closed shell lying wholly inside another shell bounds a cavity that water never
  reaches, so by default such inner shells are dropped (the void is filled) and a note says so.
  Shells that touch, overlap or stick out of one another are all solid: their union.
"""

from __future__ import annotations

import re
from pathlib import Path

import igl
import numpy as np
import torch
import trimesh

from dipnet.core.optional import optional_import
from dipnet.shapes.analytic import BALL_RADIUS_MM
from dipnet.shapes.base import Shape, ShapeError, check_dips, check_radius
from dipnet.shapes.divergence import PlaneSweep, boundary_volume_below
from dipnet.shapes.holes import boundary_caps


class MeshShape(Shape):
    """A 3D shape bounded by a triangle mesh (mm, grid frame).

    Use :func:`load_mesh` for files and :func:`from_trimesh` for in-memory meshes: they repair,
    fill sealed voids and position the mesh. The constructor takes the mesh as it is.

    Args:
        mesh: outward-oriented triangle mesh in mm.
        name: a label.
        notes: what was changed when the mesh was prepared.
        exact: False when the mesh is not watertight (volumes are then approximate).

    Attributes:
        frame_offset: (3,) mm; a point of the grid frame plus ``frame_offset`` is the same point
            in the frame of the file the mesh came from (its units times the scale): what
            :func:`from_trimesh` moved the mesh by when it centred it, so outputs can be moved back.
        frame_scale: mm per unit of that file: what :func:`from_trimesh` scaled the mesh by (``scale``, or the
            factor that brought it to ``radius``; 1 when kept as it was). A point ``p`` (mm) of the grid frame
            is ``(p + frame_offset) / frame_scale`` in the file's own coordinates and units.
        source: the file the mesh came from (``None``: built in memory), for messages that name it.
    """

    ndim = 3

    def __init__(
        self, mesh: trimesh.Trimesh, name: str = "mesh", notes: list[str] | None = None,
        exact: bool = True,
    ) -> None:
        if len(mesh.faces) == 0:
            raise ShapeError(f"mesh {name!r} has no faces")
        self.mesh = mesh
        self.name = name
        self.notes = list(notes or [])
        self.exact = exact
        self.frame_offset = np.zeros(3)
        self.frame_scale = 1.0
        self.source: str | None = None
        self._vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self._faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self._triangles = self._vertices[self._faces]  # (F, 3, 3) mm, closed by caps below
        self.volume = float(mesh.volume)
        if not exact:  # dips through an open surface: cap its holes so they are a true volume
            self._triangles, self.volume, loops = capped_surface(self._vertices, self._faces)
            if loops:
                self.notes.append(f"dips and volume through {loops} boundary loops capped by "
                                  f"{len(self._triangles) - len(self._faces)} fan triangles")

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Generalized winding number >= 0.5: ``points`` (P, 3) mm -> (P,) bool."""
        q = np.ascontiguousarray(points, dtype=np.float64)
        return igl.fast_winding_number(self._vertices, self._faces, q) >= 0.5

    def volume_below(self, directions: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
        """Volume of ``{x . theta < h}`` by the divergence theorem; (K, 3), (H,) -> (K, H) mm^3."""
        d, t = check_dips(directions, heights, 3)
        return torch.from_numpy(boundary_volume_below(self._triangles, d, t))

    def plane_sweep(self, directions: np.ndarray) -> PlaneSweep:
        """Exact ``V(h)`` and cross-sections along ``directions`` (K, 3) (the dip solver's fast path)."""
        return PlaneSweep(self._triangles, directions)

    def radius(self) -> float:
        return float(np.linalg.norm(self._vertices, axis=1).max())

    def dip_bytes_per_reading(self) -> float:
        """The plane sweep also holds every (triangle, reading) pair a water line cuts: about
        ``sqrt(F)`` triangles per plane for ``F`` evenly sized ones. Measured on icospheres
        (200,000-reading dips): 4.0 KB per reading with 320 triangles, 15 KB with 5,120."""
        return super().dip_bytes_per_reading() + 200.0 * np.sqrt(len(self._triangles))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._vertices.min(axis=0), self._vertices.max(axis=0)


def capped_surface(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float, int]:
    """A surface closed by fan caps over its boundary loops (:func:`~dipnet.shapes.holes.boundary_caps`).

    Returns ``(triangles (F + C, 3, 3) mm, enclosed volume mm^3, loops)``. Unlike the flux of
    the open surface alone, the volume does not depend on where the origin is.
    """
    v = np.asarray(vertices, dtype=np.float64)
    triangles = v[np.asarray(faces, dtype=np.int64)]
    caps, loops = boundary_caps(v, faces)
    if loops:
        triangles = np.concatenate([triangles, caps])
    top = float(np.linalg.norm(v, axis=1).max()) if len(v) else 0.0
    return triangles, float(boundary_volume_below(triangles, np.eye(3)[2:], [top])[0, 0]), loops


def inside_volume(shape: "MeshShape", n: int = 24, seed: int = 0) -> float:
    """The shape's volume by its inside test (mm^3): winding numbers at one jittered point in each
    of ``n^3`` cells of the bounding box (stratified sampling: ~1% for ``n = 24``)."""
    lo, hi = shape.bounds()
    cells = (np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
             + np.random.default_rng(seed).random((n**3, 3))) / n
    return float(shape.contains(lo + cells * (hi - lo)).mean() * np.prod(hi - lo))


def load_mesh(
    path: str | Path, radius: float | None = None, fill_sealed_voids: bool = True,
    center: bool = True, name: str | None = None, scale: float | None = None,
) -> MeshShape:
    """Read a mesh file (anything trimesh reads: PLY, STL, OBJ, OFF, GLB, ...) as a shape.

    Args:
        path: the file. A scene (e.g. GLB) is flattened into one mesh.
        radius: scale so the farthest vertex is ``radius`` mm from the centre; ``None`` keeps
            the file's units (taken as mm, times ``scale``). The shape's ``frame_scale`` keeps the factor.
        fill_sealed_voids: fill cavities bounded by closed inner shells, those lying wholly inside
            another shell (water cannot reach them). Shells that touch, overlap or stick out of
            one another are solid either way: their union.
        center: move the volume centroid (bounding-box centre if the volume is not meaningful)
            to the origin (the shape's ``frame_offset`` keeps the move).
        name: label (default: the file stem).
        scale: mm per file unit (``None``: 1), when ``radius`` is ``None`` (a scale other than 1 beside a radius is
            refused: the radius sets the size).

    Raises:
        ShapeError: the file is missing, unreadable, empty, or encloses no volume, or ``radius`` or
            ``scale`` is not a finite positive number (a scale of 0 or below would shrink the mesh to a
            point or mirror it), or the scaled mesh reaches outside ``BALL_RADIUS_MM`` (the message names the file).
    """
    if not str(path).strip():  # shape.path= left empty reads as "." (the working folder)
        raise ShapeError("no mesh file given: set its path (shape.path=/path/to/mesh.ply)")
    path = Path(path)
    if not path.is_file():
        raise ShapeError(f"mesh path {path} is a directory, not a mesh file" if path.is_dir()
                         else f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for bad files
        # trimesh falls back to decoding unparsable binary as text, which needs an optional module (a charset
        # detector); a format's own reader may need one too (lxml for .3mf): that file is not corrupt
        module = re.search(r"No module named '(\w+)", str(err)) if isinstance(err, ImportError) else None
        why = err if not isinstance(err, ImportError) else "corrupt, or not a mesh format trimesh reads"
        if module and not module.group(1).startswith(("chardet", "charset")):
            why = (f"reading a {path.suffix or 'suffixless'} file needs the Python module {module.group(1)}, which is "
                   f"not installed: pip install {module.group(1)}, or export the mesh as .ply or .stl")
        raise ShapeError(f"cannot read mesh file {path}: {why}") from err
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ShapeError(f"mesh file {path}: corrupt, or not a mesh format trimesh reads (no triangles in it)")
    if not np.isfinite(mesh.vertices).all() or mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise ShapeError(f"mesh file {path} holds non-finite vertices or face indices out of range")
    return from_trimesh(
        mesh, radius=radius, fill_sealed_voids=fill_sealed_voids, center=center,
        name=name or path.stem, source=str(path), scale=scale,
    )


def from_trimesh(
    mesh: trimesh.Trimesh, radius: float | None = None, fill_sealed_voids: bool = True,
    center: bool = True, name: str = "mesh", source: str | None = None, scale: float | None = None,
) -> MeshShape:
    """Repair, fill sealed voids, centre and scale an in-memory mesh (a copy) into a shape.

    Args: as :func:`load_mesh`; ``source`` names the origin of the mesh in messages.
    """
    where = source or name
    if radius is not None:
        check_radius(radius, f"mesh {where}: radius")
    if scale is not None and not 0 < scale < np.inf:
        raise ShapeError(f"mesh {where}: scale must be a finite, positive number of mm per file unit (1000 for a "
                         f"mesh in metres), got {scale!r}: 0 shrinks the mesh to a point, a negative scale mirrors it")
    if radius is not None and scale is not None and scale != 1:  # shape_from_file refuses the pair alike
        raise ShapeError(f"mesh {where}: radius={radius:g} and scale={scale:g} both set the mesh's size, and with a "
                         "radius the scale is ignored: give one (radius=None to take the file's units times the scale)")
    mesh = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64), process=False,
    )
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise ShapeError(f"mesh {where} has no faces or non-finite vertices")
    problems: list[str] = []
    mesh, ambiguous = _repair(mesh, problems)
    if len(mesh.faces) == 0:
        raise ShapeError(f"mesh {where} has only degenerate faces: no volume to fill")
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by zero volumes
        mesh, notes, voids = _orient_shells(mesh, fill_sealed_voids, problems)
        volume = abs(mesh.volume)
    uncertain = ambiguous / volume if volume > 0 else 0.0
    if ambiguous > 0:
        problems.append(f"its holes' rims leave {uncertain:.1%} of its volume uncertain ({ambiguous:.4g} mm^3 in the "
                        "file's units, the convex hulls of the rims: another fill of a hole bent over an edge "
                        "encloses that much more or less)")
    size = float(np.ptp(mesh.vertices, axis=0).max())
    if not volume > 1e-9 * size**3:
        raise ShapeError(f"mesh {where} encloses no volume (flat, open or empty surface)")
    shift = _centre(mesh) if center else np.zeros(3)
    mesh.apply_translation(-shift)
    factor = 1.0
    if radius is not None:
        factor = radius / float(np.linalg.norm(mesh.vertices, axis=1).max())
    elif scale is not None:
        factor = float(scale)
    size, (low, high) = factor * float(np.linalg.norm(mesh.vertices, axis=1).max()), BALL_RADIUS_MM
    if not low <= size <= high:
        raise ShapeError(f"mesh {where}: scaled by {factor:g}, its farthest point lies {size:g} mm from its centre, "
                         f"outside [{low:g}, {high:g}] mm, where its volume and dips stay finite and non-zero: check "
                         "the radius or scale")
    if factor != 1:
        mesh.apply_scale(factor)
    shape = MeshShape(mesh, name=name, exact=mesh.is_watertight)
    shape.frame_offset = factor * shift
    shape.frame_scale = factor
    shape.source = source
    if problems:
        _check_repair(shape, where)
        if uncertain > HOLE_VOLUME_TOL:
            raise ShapeError(f"mesh {where}: not watertight, and its holes' rims leave {uncertain:.1%} of its volume "
                             f"uncertain (more than {HOLE_VOLUME_TOL:.0%}: the convex hulls of the rims, how much two "
                             "fills of a hole bent over an edge can differ): close its holes in a mesh editor and load "
                             "it again")
        tail = "" if mesh.is_watertight else "; volumes and dips are approximate"
        shape._warn(f"mesh {where}: " + "; ".join(problems) + tail)
    for note in notes:  # the voids' volume in mm^3 once scaled (the file's units before), and their share
        shape._warn(f"mesh {where}: " + note.format(voids_mm3=voids * factor**3, share=voids / volume))
    return shape


#: A repaired mesh whose volume differs from its inside test's by more than this fraction is refused.
REPAIR_VOLUME_TOL = 0.2
#: A mesh whose holes' rims leave more than this fraction of its volume uncertain is refused (a truth that
#: uncertain cannot judge a reconstruction, whose volume the consistency check holds to 5 %).
HOLE_VOLUME_TOL = 0.05


def _check_repair(shape: MeshShape, where: str) -> None:
    """Refuse a repaired mesh whose volume (the dips' total) disagrees with its inside test (the
    truth occupancy): caps or shells the repair oriented wrongly, e.g. cancelling each other."""
    inside = inside_volume(shape)
    if abs(shape.volume - inside) > REPAIR_VOLUME_TOL * max(abs(inside), abs(shape.volume)):
        raise ShapeError(
            f"mesh {where}: after repair its surface encloses {shape.volume:.6g} mm^3 but its inside test (winding "
            f"numbers) holds {inside:.6g} mm^3: the repair could not close or orient the surface consistently, so "
            "dips and truth would disagree; make the mesh watertight in a mesh editor (close its holes, join its "
            "pieces, fix the normals) and load it again")


def _rim_hull_volume(mesh: trimesh.Trimesh) -> float:
    """The summed volume (mm^3) of the convex hulls of the mesh's hole rims (its loops of boundary
    edges): how far apart two fills of the holes can enclose, e.g. the two triangulations of a
    square hole bent over an edge of a box (a planar rim has none). A loop whose every vertex lies
    within 1 % of its size of another loop's is a crack between pieces, not a hole, and counts nothing."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    edges = mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    loops = [np.asarray(loop) for loop in trimesh.graph.connected_components(edges, min_len=4)]
    if not loops:
        return 0.0
    rims = np.concatenate(loops)
    owner = np.repeat(np.arange(len(loops)), [len(loop) for loop in loops])
    tree = cKDTree(mesh.vertices[rims])
    total = 0.0
    for k, loop in enumerate(loops):
        points = mesh.vertices[loop]
        near = tree.query_ball_point(points, 0.01 * np.ptp(points, axis=0).max())
        if all((owner[hits] != k).any() for hits in near):  # a crack: every vertex has another loop's beside it
            continue
        try:
            total += float(ConvexHull(points).volume)
        except QhullError:  # a flat rim: every fill encloses the same
            pass
    return total


def _repair(mesh: trimesh.Trimesh, problems: list[str]) -> tuple[trimesh.Trimesh, float]:
    """Cheap repairs (in place where possible), appending what was wrong to ``problems``; returns the
    repaired mesh and the volume its holes' rims leave uncertain (:func:`_rim_hull_volume`; 0 for a
    watertight mesh)."""
    ambiguous = 0.0
    mesh.merge_vertices()  # STL files repeat every vertex: not a problem worth a warning
    n_f = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < n_f:
        problems.append(f"removed {n_f - len(mesh.faces)} degenerate or duplicate faces")
    if not mesh.is_winding_consistent:
        optional_import("networkx", extra="repair", purpose="repairing the winding of a mesh's faces")
        before = mesh.faces.copy()
        trimesh.repair.fix_winding(mesh)
        flipped = int(np.any(mesh.faces != before, axis=1).sum())
        if 2 * flipped > len(mesh.faces):  # keep the orientation most faces had in the file
            mesh.invert()
            flipped = len(mesh.faces) - flipped
        problems.append(f"fixed the winding of {flipped} flipped faces")
    if not mesh.is_watertight:
        n_open = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        n_f = len(mesh.faces)
        optional_import("networkx", extra="repair", purpose="filling the holes of a mesh that is not watertight")
        ambiguous = _rim_hull_volume(mesh)
        trimesh.repair.fill_holes(mesh)
        filled = len(mesh.faces) - n_f
        msg = f"not watertight ({n_open} boundary edges)"
        if filled:
            msg += f", filled small holes with {filled} faces"
        if not mesh.is_watertight:
            left = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
            msg += f", {left} boundary edges remain (inside test by winding numbers)"
        problems.append(msg)
    return mesh, ambiguous


def _orient_shells(
    mesh: trimesh.Trimesh, fill_sealed_voids: bool, problems: list[str]
) -> tuple[trimesh.Trimesh, list[str], float]:
    """Orient every shell by its nesting depth, fill (drop) the sealed voids, merge the solid: ``(solid, notes,
    the voids' volume in the file's units)``, the notes formatted by the caller with ``voids_mm3`` (that volume
    scaled to mm^3) and ``share`` (of the solid's volume).

    A shell's depth is the number of other shells it lies wholly inside (:func:`_nesting_depths`).
    A shell at even depth (0: outermost) bounds solid and must enclose positive volume; at odd
    depth it bounds a sealed void and must enclose negative volume. With ``fill_sealed_voids``
    every nested shell is dropped (voids filled, and solid islands inside them become redundant).
    The outermost shells (those separate, touching, overlapping or sticking out of one another)
    are merged into their union (:func:`_union_overlapping`), so overlaps count once.
    """
    shells = [s for s in mesh.split(only_watertight=False) if s.area > 0]
    if len(shells) <= 1:
        shell = shells[0] if shells else mesh
        if _enclosed_volume(shell) < 0:
            shell.invert()
            problems.append("the surface was inside out (inverted)")
        return shell, [], 0.0
    depth = _nesting_depths(shells)
    notes: list[str] = []
    inverted = 0
    outer, nested = [], []
    for shell, k in zip(shells, depth):
        if fill_sealed_voids and k > 0:
            continue
        if (_enclosed_volume(shell) < 0) != (k % 2 == 1):
            shell.invert()
            inverted += 1
        (nested if k > 0 else outer).append(shell)
    if inverted:
        problems.append(f"inverted {inverted} of {len(shells)} shells to match their nesting")
    voids = [abs(s.volume) for s, k in zip(shells, depth) if k % 2 == 1]
    if voids:
        if fill_sealed_voids:
            notes.append(
                f"filled {len(voids)} sealed inner void(s) of total volume {{voids_mm3:.6g}} mm^3, {{share:.1%}} of "
                "the solid (water cannot reach them, so they displace water like solid)"
            )
        else:
            notes.append(
                f"kept {len(voids)} sealed inner void(s) of total volume {{voids_mm3:.6g}} mm^3, {{share:.1%}} of "
                "the solid (fill_sealed_voids=False: they are counted as water, which is unphysical)"
            )
    solid = trimesh.util.concatenate(outer)
    if len(outer) > 1:
        solid = _union_overlapping(outer, solid, problems)
    return (trimesh.util.concatenate([solid, *nested]) if nested else solid), notes, float(np.sum(voids))


def _enclosed_volume(shell: trimesh.Trimesh) -> float:
    """Signed volume (mm^3) a shell encloses: trimesh's for a closed shell; an open one's is capped
    over its holes first (the flux through an open surface depends on where the origin is, so
    its sign does not tell the orientation: a piece facing the origin came out negative)."""
    if shell.is_watertight:
        return float(shell.volume)
    return capped_surface(shell.vertices, shell.faces)[1]


def _union_overlapping(
    shells: list[trimesh.Trimesh], merged: trimesh.Trimesh, problems: list[str]
) -> trimesh.Trimesh:
    """Boolean union of outer shells that overlap (their volumes would otherwise count twice)."""
    if not all(s.is_watertight for s in shells):
        problems.append(
            f"{len(shells)} separate outer shells, not all closed: overlaps may count twice"
        )
        return merged
    optional_import("manifold3d", extra="repair", purpose="merging overlapping mesh shells")
    try:
        union = trimesh.boolean.union(shells, engine="manifold")
    except Exception as err:  # the boolean failed: keep the shells as they are
        problems.append(f"{len(shells)} outer shells could not be merged ({err})")
        return merged
    overlap = merged.volume - union.volume
    if overlap <= 1e-9 * merged.volume:
        return merged
    problems.append(
        f"merged {len(shells)} overlapping outer shells (overlap {overlap:.6g} mm^3 in the file's units, "
        f"{overlap / merged.volume:.1%} of the shells' volume)"
    )
    return union


def _nesting_depths(shells: list[trimesh.Trimesh], n_samples: int = 1000, seed: int = 0) -> np.ndarray:
    """Number of other shells that wholly contain each shell.

    Shell ``B`` lies inside shell ``A`` when its bounding box lies within ``A``'s and every vertex of
    ``B`` and ``n_samples`` points drawn on its surface (area-weighted, by ``seed``) have a winding
    number of magnitude at least 0.5 about ``A`` (either orientation: shells are oriented after
    this). A shell that touches ``A`` from outside (a box standing on another's face), overlaps it
    or sticks out of it (a pin pressed into a block) has points outside ``A``: it is not nested in
    ``A`` but part of the solid with it. A point on ``A``'s own surface has an undecided winding
    number (0.125 at a box's corner), so a shell touching ``A``'s wall from within may count as not
    nested; it then joins the solid, which fills it just the same. Two shells found inside each
    other (one surface meshed twice) are nested in neither: both join the solid.
    """
    lows = np.array([s.bounds[0] for s in shells])
    highs = np.array([s.bounds[1] for s in shells])
    slack = 1e-9 * float(np.ptp(np.concatenate([lows, highs]), axis=0).max())
    probes = [np.concatenate([s.vertices, trimesh.sample.sample_surface(s, n_samples, seed=seed)[0]])
              for s in shells]
    within = np.zeros((len(shells), len(shells)), dtype=bool)  # within[i, j]: shell i lies inside shell j
    for j, outer in enumerate(shells):
        fits = np.all((lows >= lows[j] - slack) & (highs <= highs[j] + slack), axis=1)
        fits[j] = False
        candidates = np.flatnonzero(fits)
        if len(candidates) == 0:
            continue
        q = np.ascontiguousarray(np.concatenate([probes[i] for i in candidates]), dtype=np.float64)
        v = np.ascontiguousarray(outer.vertices, dtype=np.float64)
        f = np.ascontiguousarray(outer.faces, dtype=np.int64)
        inside = np.abs(igl.fast_winding_number(v, f, q)) >= 0.5
        ends = np.cumsum([len(probes[i]) for i in candidates])
        within[candidates, j] = np.logical_and.reduceat(inside, np.concatenate([[0], ends[:-1]]))
    return (within & ~within.T).sum(axis=1)  # two shells inside each other bound the same solid


def _centre(mesh: trimesh.Trimesh) -> np.ndarray:
    """Volume centroid (mm) of a watertight mesh, bounding-box centre otherwise."""
    if mesh.is_watertight and mesh.volume > 0:
        return np.asarray(mesh.center_mass, dtype=np.float64)
    return mesh.bounds.mean(axis=0)
