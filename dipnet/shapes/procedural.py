"""Procedural solids by seed: the features that make dips hard, at any resolution.

A :class:`ProceduralSolid` is an inside test on points of the unit ball (coordinates ``u``,
dimensionless), built from a seed by one of the :data:`FAMILIES`:

* ``limbs``: a small core with 3-6 thin capsules (radius 0.05-0.09) reaching out to the ball's
  edge and 1-2 thin plates (thickness 0.06-0.1) at random rotations;
* ``polyhedron``: a random convex polyhedron (8-14 half-spaces) united with 1-3 boxes and cut by
  0-2 boxes, all at random rotations: flat faces at many angles;
* ``holes``: a rotated slab, box or ellipsoid drilled through by ``genus`` = 1-3 cylinders
  (through-holes; Euler characteristic ``1 - genus``);
* ``cavity``: a box or ellipsoid holding 1-2 spherical cavities (radius 0.17-0.25), each reached
  from outside by a channel (radius 0.07-0.09) so water fills it (the complement stays connected);
* ``blob``: a metaball field of 4-9 anisotropic Gaussians (organic, smooth);
* ``organic``: an animal- or toy-like body: an ellipsoid trunk with a head, 0-4 tapered limbs and
  sometimes a ring handle (a torus, genus 1), blended by a smooth minimum of their signed distances
  (smooth saddles where parts meet, no creases).

Every solid is centred on its centroid and scaled so that its farthest point is at radius 1
(measured on a 48^3 sampling), so ``solid.occupancy(n, fill)`` fills a grid like the benchmark's
meshes (``fill`` = farthest point / half the grid's side). :func:`generated_shape` turns one into
a :class:`~dipnet.shapes.mesh.MeshShape` in mm for the simulator (dips exact on the
marching-cubes surface of the solid at ``mesh_resolution``; the inside test stays analytic).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

from dipnet.core.grid import Grid
from dipnet.shapes.base import ShapeError, check_radius
from dipnet.shapes.mesh import MeshShape

FAMILIES = ("limbs", "polyhedron", "holes", "cavity", "blob", "organic")
#: The families a seed draws from when none is named: ``organic`` came later and is made only when
#: named, so every seed keeps the solid it made before (the shipped prior's training seeds included).
SEED_FAMILIES = FAMILIES[:5]
Inside = Callable[[np.ndarray], np.ndarray]  # (P, 3) float64 -> (P,) bool
Distance = Callable[[np.ndarray], np.ndarray]  # (P, 3) float64 -> (P,) signed distance (< 0 inside)
_NORMALISE_N = 48  # sampling that finds the centroid and the farthest point


def _rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix ``(3, 3)`` (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _box(centre, half, rot) -> Inside:
    """Box of half sides ``half`` (3,) rotated by ``rot`` around ``centre``."""
    centre, half, rot = np.asarray(centre, float), np.asarray(half, float), np.asarray(rot, float)
    return lambda p: np.all(np.abs((p - centre) @ rot) <= half, axis=1)


def _ellipsoid(centre, axes, rot) -> Inside:
    centre, axes, rot = np.asarray(centre, float), np.asarray(axes, float), np.asarray(rot, float)
    return lambda p: (((p - centre) @ rot / axes) ** 2).sum(axis=1) <= 1.0


def _segment_projection(p: np.ndarray, a: np.ndarray, ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t, squared distance)`` of points ``p`` (P, 3) to the segment from ``a`` to ``a + ab``:
    ``t`` in ``[0, 1]`` is where along it the nearest point lies."""
    t = np.clip((p - a) @ ab / float(ab @ ab), 0.0, 1.0)
    return t, ((p - a - t[:, None] * ab) ** 2).sum(axis=1)


def _capsule(a, b, radius: float) -> Inside:
    """Points within ``radius`` of the segment ``a``-``b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return lambda p: _segment_projection(p, a, b - a)[1] <= radius**2


def _cylinder(centre, axis, radius: float) -> Inside:
    """Infinite cylinder of ``radius`` along unit ``axis`` through ``centre``."""
    centre, axis = np.asarray(centre, float), np.asarray(axis, float) / np.linalg.norm(axis)

    def inside(p: np.ndarray) -> np.ndarray:
        d = p - centre
        return (d**2).sum(axis=1) - (d @ axis) ** 2 <= radius**2
    return inside


def _union(*parts: Inside) -> Inside:
    return lambda p: np.logical_or.reduce([f(p) for f in parts])


def _minus(base: Inside, *cuts: Inside) -> Inside:
    return lambda p: base(p) & ~np.logical_or.reduce([f(p) for f in cuts]) if cuts else base(p)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _limbs(rng: np.random.Generator, info: dict) -> Inside:
    parts = [_ellipsoid(np.zeros(3), rng.uniform(0.15, 0.3, 3), _rotation(rng))]
    n_limbs = int(rng.integers(3, 7))
    for _ in range(n_limbs):
        tip = _unit(rng) * rng.uniform(0.6, 0.95)
        parts.append(_capsule(np.zeros(3), tip, rng.uniform(0.05, 0.09)))
    n_plates = int(rng.integers(1, 3))
    for _ in range(n_plates):
        half = [rng.uniform(0.3, 0.55), rng.uniform(0.2, 0.45), rng.uniform(0.03, 0.05)]
        parts.append(_box(_unit(rng) * rng.uniform(0.0, 0.2), half, _rotation(rng)))
    info.update(limbs=n_limbs, plates=n_plates)
    return _union(*parts)


def _polyhedron(rng: np.random.Generator, info: dict) -> Inside:
    normals = np.stack([_unit(rng) for _ in range(int(rng.integers(8, 15)))])
    offsets = rng.uniform(0.35, 0.65, len(normals))

    def hull(p: np.ndarray) -> np.ndarray:
        return np.all(p @ normals.T <= offsets, axis=1)
    boxes = [_box(_unit(rng) * rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.4, 3), _rotation(rng))
             for _ in range(int(rng.integers(1, 4)))]
    cuts = [_box(_unit(rng) * rng.uniform(0.4, 0.7), rng.uniform(0.1, 0.3, 3), _rotation(rng))
            for _ in range(int(rng.integers(0, 3)))]
    info.update(faces=len(normals), boxes=len(boxes), cuts=len(cuts))
    return _minus(_union(hull, *boxes), *cuts)


def _holes(rng: np.random.Generator, info: dict) -> Inside:
    genus = int(rng.integers(1, 4))
    rot = _rotation(rng)
    kind = ("slab", "box", "ellipsoid")[int(rng.integers(3))]
    if kind == "slab":
        half = np.array([rng.uniform(0.6, 0.75), rng.uniform(0.45, 0.6), rng.uniform(0.12, 0.2)])
    else:
        half = np.array([rng.uniform(0.6, 0.75), rng.uniform(0.5, 0.6), rng.uniform(0.3, 0.4)])
    base = _box(np.zeros(3), half, rot) if kind != "ellipsoid" else _ellipsoid(np.zeros(3), half * 1.15, rot)
    # holes along the thinnest (local z) axis, spread along local x so that they never merge
    radius = min(0.11, rng.uniform(0.08, 0.14) * 3 / (genus + 1.5))
    xs = (np.arange(genus) - (genus - 1) / 2) * (1.2 * half[0] / genus)
    ys = rng.uniform(-0.3, 0.3, genus) * (half[1] - radius) * (1 if kind != "ellipsoid" else 0.4)
    drills = [_cylinder(rot @ np.array([x, y, 0.0]), rot[:, 2], radius) for x, y in zip(xs, ys)]
    info.update(genus=genus, base=kind, hole_radius=float(radius))
    return _minus(base, *drills)


def _cavity(rng: np.random.Generator, info: dict) -> Inside:
    rot = _rotation(rng)
    half = rng.uniform(0.55, 0.7, 3)
    ellipsoid = bool(rng.integers(2))
    base = _ellipsoid(np.zeros(3), half * 1.2, rot) if ellipsoid else _box(np.zeros(3), half, rot)
    n_cav = int(rng.integers(1, 3))
    centres = [rot @ np.array([(i - (n_cav - 1) / 2) * 0.55, 0.0, 0.0]) for i in range(n_cav)]
    radii = [rng.uniform(0.17, 0.22 if n_cav == 2 else 0.25) for _ in range(n_cav)]
    voids: list[Inside] = []
    for c, r in zip(centres, radii):
        voids.append(_ellipsoid(c, [r, r, r], np.eye(3)))
        out = rot @ np.array([0.0, rng.choice([-1.0, 1.0]), rng.choice([-1.0, 1.0])])  # towards a face
        voids.append(_capsule(c, c + 2.0 * out / np.linalg.norm(out), rng.uniform(0.07, 0.09)))
    info.update(cavities=n_cav, cavity_centres=[c.tolist() for c in centres], cavity_radii=radii)
    return _minus(base, *voids)


def _blob(rng: np.random.Generator, info: dict) -> Inside:
    n = int(rng.integers(4, 10))
    centres = np.stack([_unit(rng) * rng.uniform(0.0, 0.5) for _ in range(n)])
    inverse = [_rotation(rng) / rng.uniform(0.15, 0.35, 3) for _ in range(n)]  # columns scaled by 1/sigma
    weights = rng.uniform(0.7, 1.3, n)

    def inside(p: np.ndarray) -> np.ndarray:
        total = np.zeros(len(p))
        for c, m, w in zip(centres, inverse, weights):
            total += w * np.exp(-0.5 * (((p - c) @ m) ** 2).sum(axis=1))
        return total >= 0.5
    info.update(metaballs=n)
    return inside


def _ellipsoid_distance(centre, axes, rot) -> Distance:
    """A signed distance bound of an ellipsoid (exact on spheres)."""
    centre, axes, rot = np.asarray(centre, float), np.asarray(axes, float), np.asarray(rot, float)
    return lambda p: (np.linalg.norm((p - centre) @ rot / axes, axis=1) - 1.0) * axes.min()


def _cone_capsule_distance(a, b, radius_a: float, radius_b: float) -> Distance:
    """Distance to the segment ``a``-``b`` minus a radius tapering linearly from ``radius_a`` to ``radius_b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)

    def distance(p: np.ndarray) -> np.ndarray:
        t, squared = _segment_projection(p, a, b - a)
        return np.sqrt(squared) - (radius_a + (radius_b - radius_a) * t)
    return distance


def _torus_distance(centre, major: float, minor: float, rot) -> Distance:
    """Signed distance of a torus around the local z axis (rotated by ``rot``)."""
    centre, rot = np.asarray(centre, float), np.asarray(rot, float)

    def distance(p: np.ndarray) -> np.ndarray:
        q = (p - centre) @ rot
        return np.hypot(np.hypot(q[:, 0], q[:, 1]) - major, q[:, 2]) - minor
    return distance


def _smooth_union(parts: list[Distance], k: float) -> Inside:
    """Inside the polynomial smooth minimum (blend width ``k``) of signed distances."""
    def inside(p: np.ndarray) -> np.ndarray:
        d = parts[0](p)
        for part in parts[1:]:
            e = part(p)
            h = np.clip(0.5 + 0.5 * (e - d) / k, 0.0, 1.0)
            d = e + (d - e) * h - k * h * (1.0 - h)
        return d <= 0.0
    return inside


def _organic(rng: np.random.Generator, info: dict) -> Inside:
    rot = _rotation(rng)
    trunk = np.array([rng.uniform(0.4, 0.6), rng.uniform(0.25, 0.4), rng.uniform(0.2, 0.35)])
    parts = [_ellipsoid_distance(np.zeros(3), trunk, rot)]
    has_head = bool(rng.random() < 0.8)
    if has_head:
        neck = rot @ np.array([trunk[0] * rng.uniform(0.8, 1.1), 0.0, trunk[2] * rng.uniform(0.0, 0.9)])
        parts.append(_ellipsoid_distance(neck, rng.uniform(0.14, 0.26, 3), _rotation(rng)))
    n_limbs = int(rng.integers(0, 5))
    for i in range(n_limbs):  # legs from the underside, fins or arms: tapered, reaching outwards
        side = 1.0 if i % 2 else -1.0
        root = rot @ np.array([trunk[0] * rng.uniform(-0.6, 0.6), side * trunk[1] * 0.5, -trunk[2] * 0.5])
        reach = rot @ np.array([rng.uniform(-0.2, 0.2), side * rng.uniform(0.0, 0.35), -rng.uniform(0.3, 0.55)])
        radius = rng.uniform(0.07, 0.13)
        parts.append(_cone_capsule_distance(root, root + reach, radius, radius * rng.uniform(0.5, 1.0)))
    has_ring = bool(rng.random() < 0.3)
    if has_ring:  # a handle or tail loop: a genus-1 smooth part
        parts.append(_torus_distance(rot @ np.array([-trunk[0], 0.0, 0.0]), rng.uniform(0.2, 0.35),
                                     rng.uniform(0.06, 0.12), _rotation(rng)))
    blend = rng.uniform(0.05, 0.15)
    info.update(head=has_head, limbs=n_limbs, ring=has_ring, blend=float(blend))
    return _smooth_union(parts, blend)


_BUILDERS: dict[str, Callable[[np.random.Generator, dict], Inside]] = {
    "limbs": _limbs, "polyhedron": _polyhedron, "holes": _holes, "cavity": _cavity, "blob": _blob,
    "organic": _organic}


def _lattice(n: int, supersample: int) -> list[np.ndarray]:
    """Sub-voxel sample points of an ``n^3`` grid on ``[-1, 1]^3``, one ``(n^3, 3)`` array ``(x, y, z)``
    (array order ``[z, y, x]``) per sub-voxel offset."""
    h = 2.0 / n
    axis = -1.0 + (np.arange(n) + 0.5) * h
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    centres = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5) * h
    return [centres + np.array([ox, oy, oz]) for oz in offsets for oy in offsets for ox in offsets]


@dataclass
class ProceduralSolid:
    """A solid in the unit ball from :func:`make_solid` (coordinates dimensionless).

    Attributes:
        family: one of :data:`FAMILIES`.
        seed: the seed that made it.
        info: what the seed drew (e.g. ``genus``, ``cavities``, ``cavity_centres`` in the solid's
            own frame before normalisation: use :meth:`to_unit` to map them).
        centre, scale: normalisation: ``u = (v - centre) * scale`` maps the raw frame ``v`` to the
            unit frame ``u`` in which the farthest point is at radius 1.
    """

    family: str
    seed: int
    raw: Inside
    info: dict = field(default_factory=dict)
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def contains(self, u: np.ndarray) -> np.ndarray:
        """Inside test in the unit frame: ``(P, 3)`` -> ``(P,)`` bool (false outside the unit ball)."""
        u = np.asarray(u, dtype=np.float64)
        return self.raw(u / self.scale + self.centre) & ((u**2).sum(axis=1) <= 1.0 + 1e-9)

    def to_unit(self, v: np.ndarray) -> np.ndarray:
        """Raw-frame points ``(..., 3)`` (e.g. ``info["cavity_centres"]``) in the unit frame."""
        return (np.asarray(v, dtype=np.float64) - self.centre) * self.scale

    def occupancy(self, n: int, fill: float = 0.9, supersample: int = 2) -> np.ndarray:
        """Partial-volume occupancy on an ``n^3`` grid whose half side is 1 / ``fill`` solid radii.

        Args:
            n: grid resolution.
            fill: the solid's farthest point / half the grid's side (0 < fill <= 1).
            supersample: ``s``: each voxel is the fraction of ``s^3`` sub-voxel points inside.

        Returns:
            float32 array ``(n, n, n)`` indexed ``[z, y, x]``, values in ``[0, 1]``.
        """
        if not 0 < fill <= 1 or int(n) < 2 or int(supersample) < 1:
            raise ValueError(f"need n >= 2, 0 < fill <= 1 and supersample >= 1, got {n}, {fill}, {supersample}")
        total = np.zeros(int(n) ** 3)
        for pts in _lattice(int(n), int(supersample)):
            total += self.contains(pts / fill)
        return (total / int(supersample) ** 3).reshape((int(n),) * 3).astype(np.float32)


def make_solid(seed: int, family: str | None = None) -> ProceduralSolid:
    """The solid of ``seed`` (family drawn from :data:`SEED_FAMILIES` by the seed when ``None``),
    normalised to the unit ball.

    Raises:
        ValueError: unknown family.
        ShapeError: the seed drew an empty solid.
    """
    rng = np.random.default_rng([int(seed), 0x5EED])
    if family is None:
        family = SEED_FAMILIES[int(rng.integers(len(SEED_FAMILIES)))]
    if family not in _BUILDERS:
        raise ValueError(f"unknown shape family {family!r}; choose one of {FAMILIES}")
    info: dict = {}
    raw = _BUILDERS[family](rng, info)
    solid = ProceduralSolid(family, int(seed), raw, info, np.zeros(3), 1.0)
    pts = np.concatenate(_lattice(_NORMALISE_N, 1)) * 1.5  # raw solids stay within radius 1.5
    inside = pts[raw(pts)]
    if len(inside) == 0:
        raise ShapeError(f"procedural solid {family} seed {seed} is empty")
    solid.centre = inside.mean(axis=0)
    solid.scale = 1.0 / (np.linalg.norm(inside - solid.centre, axis=1).max() + 1.5 * 3.0 / _NORMALISE_N)
    return solid


def family_of(seed: int) -> str:
    """The family :func:`make_solid` draws for ``seed`` when none is given."""
    return make_solid(seed).family


#: the finest marching-cubes grid of a generated shape (512^3 samples: 1 GB in float64)
MAX_MESH_RESOLUTION = 512


def generated_shape(seed: int = 0, family: str | None = None, radius: float = 45.0, mesh_resolution: int = 128,
                    ndim: int = 3) -> GeneratedShape:
    """The procedural solid of ``seed`` as a shape in mm whose farthest point is ``radius`` mm
    from the origin (``conf/shape/generated.yaml``).

    Args:
        seed: which solid.
        family: one of :data:`FAMILIES` or ``None`` (drawn from the seed).
        radius: mm.
        mesh_resolution: the marching-cubes grid (over the solid's bounding cube) whose surface
            gives the exact dips and the volume.
        ndim: must be 3.
    """
    if int(ndim) != 3:
        raise ShapeError("generated shapes are 3D (ndim=3)")
    radius = check_radius(radius)  # before the solid is made
    return GeneratedShape(make_solid(seed, family), radius, int(mesh_resolution))


class GeneratedShape(MeshShape):
    """A :class:`ProceduralSolid` scaled to ``radius`` mm: analytic inside test, dips and volume from
    its marching-cubes surface at ``mesh_resolution`` (a closed mesh, so they are exact for it)."""

    def __init__(self, solid: ProceduralSolid, radius: float, mesh_resolution: int = 128) -> None:
        from skimage import measure

        self.solid, self.radius_mm = solid, float(radius)
        n = int(mesh_resolution)
        if n > MAX_MESH_RESOLUTION:  # 100000 failed as "MemoryError((1000000000000000,), dtype('float64'))"
            raise ValueError(f"shape.mesh_resolution must be at most {MAX_MESH_RESOLUTION} (marching-cubes cells per "
                             f"axis: {n}^3 samples of the solid do not fit in memory), got {mesh_resolution!r}")
        occ = np.pad(solid.occupancy(n, fill=1.0, supersample=1), 1)
        verts, faces, _, _ = measure.marching_cubes(occ, level=0.5)
        verts = ((verts[:, ::-1] - 0.5) * (2.0 / n) - 1.0) * radius  # (z, y, x) index -> (x, y, z) mm
        mesh = trimesh.Trimesh(vertices=verts, faces=faces[:, ::-1], process=False)
        if mesh.volume < 0:
            mesh.invert()
        note = f"procedural {solid.family} solid, seed {solid.seed}; dips from its {n}^3 marching-cubes surface"
        super().__init__(mesh, name=f"generated_{solid.family}_{solid.seed}", exact=bool(mesh.is_watertight),
                         notes=[note])

    def contains(self, points: np.ndarray) -> np.ndarray:
        """The analytic inside test: ``points`` (P, 3) mm -> (P,) bool."""
        return self.solid.contains(np.asarray(points, dtype=np.float64) / self.radius_mm)

    def radius(self) -> float:
        """The solid's farthest point from the origin, mm."""
        return self.radius_mm

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The cube around the ball of :meth:`radius` (the analytic solid may reach a little beyond
        its mesh)."""
        return np.full(3, -self.radius_mm), np.full(3, self.radius_mm)


def generated_occupancy(seed: int, grid: Grid, fill: float = 0.9, family: str | None = None,
                        supersample: int = 2) -> np.ndarray:
    """Occupancy of the solid of ``seed`` on ``grid`` (3D) filling ``fill`` of the working ball
    (the farthest point at ``fill * grid.radius``), ``grid.shape`` float32 in ``[0, 1]``."""
    if grid.ndim != 3:
        raise ShapeError("generated shapes are 3D")
    return make_solid(seed, family).occupancy(grid.n, fill * grid.radius / (grid.extent / 2), supersample)


__all__ = ["FAMILIES", "SEED_FAMILIES", "GeneratedShape", "ProceduralSolid", "family_of", "generated_occupancy",
           "generated_shape", "make_solid"]
