"""Air trapped in cavities, and cavities still dry, while an object is dipped: the dip transform's "caps".

The dip transform assumes water reaches every part of the object's surroundings as soon as the water line
passes it. Two kinds of cavity break that (the paper's "caps", in its limitations):

* **air pockets**: a cavity that opens downward (a bell) keeps its air once the water closes its mouth: the
  air cannot leave without going down through the water. From then on it displaces water like solid
  material, for the rest of the dip (the air's compression, about 1 % per 100 mm of water, is ignored).
* **vessels**: a cavity that opens upward (a cup) stays dry while the water line climbs its outside, and
  displaces water like a boat hull, until the water reaches its rim and pours in. While it floods the
  water stands at the rim (in the object's frame), so the level *falls* as the object goes down.

Both are found on a voxel grid of the shape (``resolution`` cells per axis over its bounding box, one
empty layer around it) for each dip direction ``theta``, with ``h = x . theta`` the height of a cell:

* ``escape(x)``: the highest level air at ``x`` can keep while leaving: the largest, over paths through
  empty cells from ``x`` to the open border, of the lowest height on the path (a grey reconstruction by
  dilation, :func:`skimage.morphology.reconstruction`, 6-connected). Air at ``x`` is trapped once the water
  is above ``escape(x)``, and ``escape(x) < h(x)`` means it must go down to leave: a pocket cell.
* ``flood(x)``: the lowest level at which the water reaches ``x`` from the open border: the smallest, over
  paths, of the highest height on the path (reconstruction by erosion). ``flood(x) > h(x)``: a vessel cell,
  dry while ``h(x) < t < flood(x)``.

A cell counts only when it lies more than one cell's extent along ``theta`` (``vs (|th_1| + ... )``) below
its escape or above its flood level, so the staircase of a voxelised wall traps nothing. What a dip then
displaces at water line ``t`` is ``V(t) + P(t)``, ``P(t) = sum_x v [h(x) < t] ([pocket] + [vessel][t <
flood(x)])`` (a pocket cell that is also a vessel cell counts once), each cell's volume ``v`` spread
uniformly over its extent along ``theta``, tabulated (:class:`CavityCurve`). ``V + P`` falls where a vessel
floods, so ``A delta = V + P`` keeps a single root (``A delta - V - P`` still rises with ``delta``): the
dip solver (:func:`dipnet.simulator.physics.solve_dip`) needs nothing else.

Empty cells the grid cannot reach from the border at all (a channel narrower than a cell closed by the
voxels; a truly sealed void is solid in every dipnet shape already) are taken as wet, with a warning to
raise ``resolution``.

Objects without such cavities are unchanged (a ball, a box, a torus, through-holes; the bundled animals trap at
most 0.01 % of their volume). The built-in chamber box, whose chamber opens through one channel, traps 5 % of its
volume as air on average over random directions (up to 14 %), and holds a vessel of 6 % on average (up to 14 %);
the bundled boot up to 2.3 % (64 cells; ``scripts/bench_pockets.py``, docs/benchmarks/pockets.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
from scipy import ndimage
from skimage.morphology import reconstruction

#: Heights per cell width of the tabulated pocket volume ``P(t)``.
_TABLE_STEPS_PER_CELL = 8


@dataclass
class Pockets:
    """Trap air in cavities that open downward and keep cavities that open upward dry (module docstring).

    Attributes:
        resolution: cells per axis of the grid the cavities are found on (over the shape's bounding box);
            a cavity's volume is right to about one cell over its depth.
    """

    resolution: int = 64

    def __post_init__(self) -> None:
        if isinstance(self.resolution, bool) or int(self.resolution) != self.resolution \
                or not 8 <= self.resolution <= 256:
            raise ValueError(f"pockets resolution must be a whole number of cells per axis in [8, 256], "
                             f"got {self.resolution!r}")
        self.resolution = int(self.resolution)


def as_pockets(pockets: Pockets | Mapping | bool | None) -> Pockets | None:
    """``pockets`` as a :class:`Pockets` or ``None`` (off): ``True`` is the default model, a mapping its fields
    (``{resolution: 96}`` in a config), ``False`` / ``None`` off."""
    if pockets is None or pockets is False:
        return None
    if pockets is True:
        return Pockets()
    if isinstance(pockets, Pockets):
        return pockets
    if isinstance(pockets, Mapping):
        unknown = sorted(set(pockets) - {f.name for f in fields(Pockets)})
        if unknown:
            raise ValueError(f"pockets: unknown option(s) {', '.join(map(str, unknown))} (it takes resolution)")
        return Pockets(**dict(pockets))
    raise ValueError(f"pockets must be true, false, null or {{resolution: cells per axis}}, got "
                     f"{type(pockets).__name__} {pockets!r}")


class CavityGrid:
    """A shape's empty cells on a grid, for :meth:`curve` along any direction.

    Args:
        shape: a :class:`~dipnet.shapes.Shape` centred near the origin (``contains``, ``radius``, ``ndim``).
        resolution: cells per axis over ``[-R, R]`` (``R`` = the shape's radius), plus one empty layer
            on every side.
    """

    def __init__(self, shape, resolution: int) -> None:
        radius = float(shape.radius())
        self.ndim = int(shape.ndim)
        self.cell = 2.0 * radius / int(resolution)  # mm
        n = int(resolution) + 2
        axis = (np.arange(n) - n / 2 + 0.5) * self.cell
        self.centres = np.stack(np.meshgrid(*[axis] * self.ndim, indexing="ij"), axis=-1)  # (n,)*d + (d,) mm
        inside = np.asarray(shape.contains(self.centres.reshape(-1, self.ndim)), dtype=bool)
        self.empty = ~inside.reshape((n,) * self.ndim)
        self.empty[_border(self.empty.shape)] = True
        self._footprint = ndimage.generate_binary_structure(self.ndim, 1)

    @property
    def cell_volume(self) -> float:
        """One cell's volume (mm^3; mm^2 in 2D)."""
        return self.cell ** self.ndim

    def levels(self, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h, escape, flood)`` of every cell (grid-shaped, mm) along the unit ``direction`` ``(d,)``
        (module docstring); ``escape`` is ``-inf`` and ``flood`` ``+inf`` where no empty path reaches the border."""
        h = self.centres @ np.asarray(direction, dtype=np.float64)
        low, high = float(h.min()) - 1.0, float(h.max()) + 1.0
        border = _border(h.shape)
        escape = reconstruction(np.where(border, h, low), np.where(self.empty, h, low), method="dilation",
                                footprint=self._footprint)
        flood = reconstruction(np.where(border, h, high), np.where(self.empty, h, high), method="erosion",
                               footprint=self._footprint)
        unreachable = self.empty & (flood >= high)
        return h, np.where(unreachable, -np.inf, escape), np.where(unreachable, np.inf, flood)

    def curve(self, direction: np.ndarray) -> "CavityCurve":
        """The pocket volume ``P(t)`` along the unit ``direction`` ``(d,)`` (module docstring)."""
        direction = np.asarray(direction, dtype=np.float64)
        h, escape, flood = self.levels(direction)
        extent = self.cell * float(np.abs(direction).sum())  # a cell's extent along the direction, mm
        closed = self.empty & ~np.isfinite(flood)
        if closed.any():
            warnings.warn(f"pockets: {int(closed.sum())} empty cell(s) of the {self.cell:.3g} mm cavity grid have no "
                          "path to the open water (a channel narrower than a cell?): taken as wet; raise "
                          "pockets.resolution to resolve them", RuntimeWarning, stacklevel=3)
        reach = self.empty & ~closed
        pocket = reach & (escape < h - extent)
        vessel = reach & ~pocket & (flood > h + extent)
        return CavityCurve(h[pocket], h[vessel], flood[vessel], self.cell_volume, extent,
                           float(np.abs(h).max()) + extent, self.cell / _TABLE_STEPS_PER_CELL)

    def shares(self, direction: np.ndarray) -> tuple[float, float]:
        """``(pocket, vessel)``: the volume of pocket cells and of vessel cells along ``direction`` (mm^3;
        mm^2 in 2D), each cell counted once."""
        curve = self.curve(direction)
        return curve.pocket_volume, curve.vessel_volume


class CavityCurve:
    """The tabulated pocket volume ``P(t)`` and its slope ``dP/dt`` of one dip (module docstring).

    Args:
        pocket_h: heights ``(P,)`` mm of the pocket cells.
        vessel_h, vessel_flood: heights and flood levels ``(Q,)`` mm of the vessel cells.
        cell_volume: one cell's volume (mm^3; mm^2 in 2D).
        extent: a cell's extent along the direction (mm): each cell's volume is spread over it.
        reach: ``P`` is tabulated on ``[-reach, reach]`` (mm), constant beyond.
        step: the table's height step (mm); a vessel floods over one step.
    """

    def __init__(self, pocket_h: np.ndarray, vessel_h: np.ndarray, vessel_flood: np.ndarray, cell_volume: float,
                 extent: float, reach: float, step: float) -> None:
        self.pocket_volume = cell_volume * pocket_h.size
        self.vessel_volume = cell_volume * vessel_h.size
        self._t = np.arange(-reach, reach + step, step)
        rising = _spread_cdf(np.concatenate([pocket_h, vessel_h]), self._t, extent)
        flooded = _spread_cdf(vessel_flood, self._t, step)
        self._table = cell_volume * (rising - flooded)  # (T,) mm^3
        self._slope = np.diff(self._table) / step
        self._mid = 0.5 * (self._t[1:] + self._t[:-1])

    def volume_and_area(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``P(t)`` (n,) mm^3 and ``dP/dt`` (n,) mm^2 (negative where a vessel floods) at heights ``t`` (n,) mm."""
        t = np.asarray(t, dtype=np.float64)
        return (np.interp(t, self._t, self._table),
                np.interp(t, self._mid, self._slope, left=0.0, right=0.0))

    @property
    def max_volume(self) -> float:
        """The largest ``P`` over all heights (mm^3)."""
        return float(self._table.max(initial=0.0))


class CurveWithCavities:
    """A dip's curve (:func:`~dipnet.simulator.volume_curve.dip_volume_curve`) plus its pocket volume: what
    the dip displaces, ``V(t) + P(t)``, with the interface the dip solver uses."""

    monotone = False  # a vessel's flooding makes V + P fall

    def __init__(self, curve, cavities: CavityCurve) -> None:
        self._curve, self._cavities = curve, cavities
        self.total = float(curve.total) + cavities.max_volume
        self.max_area = None  # the cross-section is checked where it is evaluated

    def volume(self, t: np.ndarray) -> np.ndarray:
        """``V(t) + P(t)`` (n,) mm^3 at heights ``t`` (n,) mm."""
        return self.volume_and_area(t)[0]

    def volume_and_area(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``V + P`` (n,) mm^3 and its slope (n,) mm^2 at heights ``t`` (n,) mm."""
        volume, area = self._curve.volume_and_area(t)
        extra, extra_area = self._cavities.volume_and_area(t)
        return volume + extra, area + extra_area


def cavity_shares(shape, directions: np.ndarray, resolution: int = 64) -> np.ndarray:
    """``(K, 2)``: per direction the volume of the shape's pocket and vessel cells over its volume
    (:class:`CavityGrid`; ``directions`` ``(K, d)`` unit vectors)."""
    grid = CavityGrid(shape, resolution)
    return np.array([grid.shares(d) for d in np.asarray(directions, dtype=np.float64)]) / float(shape.volume)


def _border(shape: tuple[int, ...]) -> np.ndarray:
    """A boolean array of ``shape`` true on its outer layer of cells."""
    border = np.ones(shape, dtype=bool)
    border[(slice(1, -1),) * len(shape)] = False
    return border


def _spread_cdf(heights: np.ndarray, t: np.ndarray, width: float) -> np.ndarray:
    """``sum_i clip((t - heights_i) / width + 1/2, 0, 1)`` at every ``t`` ``(T,)``: how many of the cells at
    ``heights`` lie below ``t``, each spread uniformly over ``width`` mm about its height (``t`` evenly spaced)."""
    if heights.size == 0:
        return np.zeros_like(t)
    step = float(t[1] - t[0])
    counts = np.bincount(np.clip(np.searchsorted(t, heights), 0, t.size - 1), minlength=t.size).astype(np.float64)
    taps = max(1, int(round(width / step)))
    spread = np.convolve(counts, np.full(taps, 1.0 / taps))[: t.size]  # each count over ``taps`` table steps
    shift = taps // 2  # centre the ramp on the cell's height
    cumulative = np.cumsum(spread)
    return np.concatenate([cumulative[shift:], np.full(shift, cumulative[-1])])
