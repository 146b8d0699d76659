"""The dipping simulator's physics: tank, sensors, and the water rise while an object is lowered.

Model, per orientation ``theta`` (unit "up" vector in the object frame)
-----------------------------------------------------------------------
Heights ``t`` are measured along ``theta`` in the object frame (mm); ``V(t)`` is the volume
of the object below the plane ``x . theta = t`` (:meth:`Shape.volume_below`). At the first
reading (stage position ``s_0 = 0``) the water line sits at ``t_start = -(R + clearance)``,
below the object's bounding sphere of radius ``R``; on the ideal rig (rotation centre at the
object's origin) that holds for every orientation, a real rig's geometry
(:class:`~dipnet.core.geometry.RigGeometry`: pivot, tilt-axis offset, zero offsets, step scale,
cross-section, drift, lag) moves it per dip and :func:`simulate_scan` applies it. At reading ``i`` the stage
has lowered the object by ``s_i = i d`` and the water has risen by ``delta_i``, so the water
line is at ``t_i = t_start + s_i + delta_i`` and Archimedes gives the fixed point

    A delta_i = V(t_start + s_i + delta_i),

with ``A`` the tank's *free* cross-section at the water line. ``g(delta) = A delta - V(...)``
has slope ``A - a(t) > 0`` (``a`` = the object's cross-section, which must be smaller than
``A``), so the root is unique and bracketed by ``[V(t_start + s_i) / A, V_total / A]``. It is
found by bisection on a fine table of ``V`` and polished by safeguarded Newton steps on the
exact ``V``. Readings continue until the object is fully under water plus a few steps.

In 2D every "volume" is an area (mm^2) and the tank cross-section is a width (mm); the same
equations hold.

Sensors
-------
:class:`LevelSensor` reads the water level (mm), :class:`Balance` a tared balance under the
tank (apparent mass ``rho V`` in g). Both add white Gaussian noise (standard deviation given
directly, or from an SNR in dB, see :meth:`SensorModel.noise_sigma`), a slow linear drift in time
and quantisation, in that order.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, replace
from typing import ClassVar

import numpy as np
from tqdm.auto import tqdm

from dipnet.core.counts import is_real
from dipnet.core.rawscan import WATER_DENSITY_G_PER_MM3, OrientationScan, RawScan, ScanHeader
from dipnet.simulator.size import check_simulation
from dipnet.core.geometry import RigGeometry
from dipnet.core.orientations import direction_to_rig, unit_directions
from dipnet.simulator.pockets import CavityGrid, CurveWithCavities, Pockets, as_pockets
from dipnet.simulator.volume_curve import dip_volume_curve

_NEWTON_STEPS = 60  # most dips converge in 3-5 steps; the rest bisect inside the bracket
_RELATIVE_TOL = 1e-12  # stop when max |A delta - V| <= this x the object's volume
#: Signal-to-noise ratios (dB) a sensor accepts: from noise 10x the signal to none measurable.
SNR_DB_RANGE = (-20.0, 200.0)


def check_snr_db(snr_db: float | None) -> None:
    """Raise ``ValueError`` unless ``snr_db`` (dB) is null or a number in :data:`SNR_DB_RANGE`."""
    low, high = SNR_DB_RANGE
    if snr_db is not None and (not is_real(snr_db) or not low <= snr_db <= high):
        raise ValueError(f"snr_db must be a number of dB in [{low:g}, {high:g}] or null (noise-free), "
                         f"got {snr_db!r}")


@dataclass
class Tank:
    """The water tank.

    Attributes:
        cross_section_mm2: free cross-section ``A`` at the water line, mm^2 (in 2D: a width in
            mm). Subtract anything fixed that pierces the surface (posts, the object holder).
        rest_level_mm: water level before the object touches the water, mm (finite).
    """

    cross_section_mm2: float = 300.0 * 200.0
    rest_level_mm: float = 150.0

    def __post_init__(self) -> None:
        area = self.cross_section_mm2  # True was read as 1 mm^2, a string failed in numpy naming no option
        if not is_real(area) or not 0 < area < math.inf:
            raise ValueError(f"tank cross_section_mm2 must be a finite, positive number (mm^2; mm in 2D), got {area!r}")
        if isinstance(self.rest_level_mm, bool) or not math.isfinite(self.rest_level_mm):
            raise ValueError(f"tank rest_level_mm must be a finite level (mm), got {self.rest_level_mm!r}")

    @classmethod
    def default(cls, ndim: int) -> "Tank":
        """A 300 x 200 mm tank (3D: A = 60,000 mm^2; 2D: a 300 mm wide slot), 150 mm of water."""
        return cls(cross_section_mm2=300.0 * 200.0 if ndim == 3 else 300.0)


class SensorModel(ABC):
    """A noisy, quantised, drifting reading of the submerged volume.

    Subclasses set :attr:`quantity` and map the submerged volume to an ideal reading.
    """

    quantity: ClassVar[str]

    @abstractmethod
    def ideal(self, tank: Tank, submerged: np.ndarray) -> np.ndarray:
        """Noise-free readings for submerged volumes ``(n,)`` mm^3 (mm^2 in 2D)."""

    @abstractmethod
    def _params(self) -> tuple[float, float | None, float, float]:
        """``(sigma, snr_db, quantum, drift_per_s)`` in reading units."""

    def __post_init__(self) -> None:
        """Raise ``ValueError`` for a negative or non-finite noise, quantum or drift, an SNR out of range, or
        both a noise sigma and an SNR (the SNR sets the noise, so the sigma would be ignored without a word)."""
        unit = self.quantity.rsplit("_", 1)[-1]  # mm or g
        names = (f"sigma_{unit}", "snr_db", f"quantum_{unit}", f"drift_{unit}_per_s")
        for name, value in zip(names, self._params()):
            if name == "snr_db":
                check_snr_db(value)
                continue
            low = -math.inf if name.startswith("drift") else 0.0
            if not is_real(value) or not low <= value < math.inf:
                kind = "a finite number" if low < 0 else "a number >= 0 (0: none)"
                raise ValueError(f"sensor {name} must be {kind}, got {value!r}")
        sigma, snr_db, _, _ = self._params()
        if snr_db is not None and sigma > 0:
            raise ValueError(f"the sensor's sigma_{unit}={sigma:g} {unit} and snr_db={snr_db:g} both set its noise, "
                             f"and with snr_db the sigma is ignored: give one "
                             f"(snr_db=null for a noise of {sigma:g} {unit})")

    @property
    def quantum(self) -> float:
        return self._params()[2]

    def noise_sigma(self, ideal: np.ndarray) -> float:
        """Standard deviation of the additive noise for one orientation's ideal readings.

        With ``snr_db`` set, ``sigma = rms(r) / 10**(snr_db / 20)`` where ``r`` are the
        per-step rises of the ideal reading while the object crosses the water line (steps
        with a non-zero rise): the SNR of the dip signal, as in the paper's white noise on the
        dip samples. Otherwise the fixed ``sigma``.
        """
        sigma, snr_db, _, _ = self._params()
        if snr_db is None:
            return float(sigma)
        rises = np.diff(ideal)
        rises = rises[np.abs(rises) > 1e-9 * max(np.abs(rises).max(initial=0.0), 1e-300)]
        rms = float(np.sqrt(np.mean(rises**2))) if rises.size else 0.0
        return rms / 10.0 ** (snr_db / 20.0)

    def read(self, ideal: np.ndarray, time_s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """Measured readings ``(n,)`` for ideal readings ``(n,)`` at times ``(n,)`` s (from the
        scan start); returns ``(readings, noise sigma)``."""
        _, _, quantum, drift = self._params()
        sigma = self.noise_sigma(ideal)
        out = ideal + drift * time_s
        if sigma > 0:
            out = out + rng.normal(0.0, sigma, size=ideal.shape)
        if quantum > 0:
            out = np.round(out / quantum) * quantum
        return out, sigma

    def to_dict(self) -> dict:
        return {"kind": type(self).__name__, "quantity": self.quantity, **asdict(self)}


@dataclass
class LevelSensor(SensorModel):
    """Water-level transducer (mm).

    Attributes:
        sigma_mm: white noise standard deviation per reading (mm); 0 with ``snr_db`` set (both: ``ValueError``).
        snr_db: noise from a signal-to-noise ratio instead (see :meth:`SensorModel.noise_sigma`).
        quantum_mm: reading resolution (mm); 0 (default) for none. The authors' robot: 0.04 mm.
            Mind the scale: one quantum is ``quantum_mm * A`` mm^3 (600 mm^3 for 0.01 mm in a
            300 x 200 mm tank), which for a small object is several percent of a slab.
        drift_mm_per_s: slow linear drift of the reading (mm/s).
        seed: default random seed of the noise.
    """

    sigma_mm: float = 0.0
    snr_db: float | None = None
    quantum_mm: float = 0.0
    drift_mm_per_s: float = 0.0
    seed: int = 0
    quantity: ClassVar[str] = "level_mm"

    def ideal(self, tank: Tank, submerged: np.ndarray) -> np.ndarray:
        return tank.rest_level_mm + submerged / tank.cross_section_mm2

    def _params(self):
        return self.sigma_mm, self.snr_db, self.quantum_mm, self.drift_mm_per_s


@dataclass
class Balance(SensorModel):
    """A tared balance under the tank: apparent mass ``rho V`` (g) of the displaced liquid.

    Attributes:
        sigma_g, snr_db, quantum_g, drift_g_per_s, seed: as for :class:`LevelSensor`, in g.
        density_g_per_mm3: liquid density (water: 1e-3 g/mm^3).
    """

    sigma_g: float = 0.0
    snr_db: float | None = None
    quantum_g: float = 0.01
    drift_g_per_s: float = 0.0
    density_g_per_mm3: float = WATER_DENSITY_G_PER_MM3
    seed: int = 0
    quantity: ClassVar[str] = "mass_g"

    def __post_init__(self) -> None:
        """As :meth:`SensorModel.__post_init__`, and a ``ValueError`` for a density (g/mm^3) that is not a finite,
        positive number (``true`` was read as 1 g/mm^3, a thousand times water's, exit 0)."""
        super().__post_init__()
        density = self.density_g_per_mm3
        if not is_real(density) or not 0 < density < math.inf:
            raise ValueError(f"sensor density_g_per_mm3 must be a finite, positive number (g/mm^3; water 1e-3), "
                             f"got {density!r}")

    def ideal(self, tank: Tank, submerged: np.ndarray) -> np.ndarray:
        return self.density_g_per_mm3 * submerged

    def _params(self):
        return self.sigma_g, self.snr_db, self.quantum_g, self.drift_g_per_s


@dataclass
class DipProtocol:
    """How each orientation is dipped.

    Attributes:
        step_mm: stage step ``d`` (mm).
        clearance_mm: gap between the water and the bottom of the object's bounding sphere at
            the first reading (mm); the readings until contact give the baseline.
        extra_steps: readings after the object is fully under water.
        settle_s: time per step (move + settling) before each reading (s).
        reorient_s: time between orientations (lift, rotate, lower) (s).

    Every value must be finite and not negative (``step_mm`` positive, ``extra_steps`` whole), else a
    ``ValueError`` names it.
    """

    step_mm: float = 1.0
    clearance_mm: float = 3.0
    extra_steps: int = 3
    settle_s: float = 2.0
    reorient_s: float = 30.0

    def __post_init__(self) -> None:
        # is_real first: True was a 1 mm step, and text or null failed as a TypeError naming no option
        if not is_real(self.step_mm) or not 0 < self.step_mm < math.inf:
            raise ValueError(f"step_mm must be a finite, positive number (mm), got {self.step_mm!r}")
        for name, unit in (("clearance_mm", "mm"), ("settle_s", "s"), ("reorient_s", "s")):
            value = getattr(self, name)
            if not is_real(value) or not 0 <= value < math.inf:  # NaN fails too
                raise ValueError(f"protocol {name} must be a finite number >= 0 ({unit}), got {value!r}")
        if not is_real(self.extra_steps) or not 0 <= self.extra_steps < math.inf \
                or int(self.extra_steps) != self.extra_steps:
            raise ValueError(f"protocol extra_steps must be a whole number of readings >= 0, got {self.extra_steps!r}")
        self.extra_steps = int(self.extra_steps)

    def n_readings(self, radius: float) -> int:
        """Readings per orientation for an object of bounding radius ``radius`` (mm)."""
        return int(np.ceil((2 * radius + self.clearance_mm) / self.step_mm)) + 1 + self.extra_steps


@dataclass
class DipState:
    """The exact physical state at every reading of one orientation (all ``(n,)`` float64).

    Attributes:
        stage_mm: stage positions ``s_i`` (mm).
        rise_mm: water rise ``delta_i`` (mm).
        waterline_mm: water line height in the object frame ``t_i = t_start + s_i + delta_i``.
        submerged: displaced volume ``A delta_i`` (mm^3; mm^2 in 2D): the submerged volume ``V(t_i)``, plus
            trapped air and dry vessels with :class:`~dipnet.simulator.pockets.Pockets`.
        residual: ``max |A delta_i - V(t_i)|`` with the exact ``V`` (mm^3).
        pocket_mm3, vessel_mm3: the volume of the cavities that trap air along this dip, and of those that stay
            dry until the water reaches their rim (:class:`~dipnet.simulator.pockets.CavityGrid`; 0 without pockets).
    """

    stage_mm: np.ndarray
    rise_mm: np.ndarray
    waterline_mm: np.ndarray
    submerged: np.ndarray
    residual: float
    pocket_mm3: float = 0.0
    vessel_mm3: float = 0.0


def solve_dip(shape, direction, tank: Tank, stage_mm: np.ndarray, t_start_mm: float,
              cavities: CavityGrid | None = None) -> DipState:
    """Solve ``A delta = V(t_start + s + delta)`` for every stage position (see module docstring).

    Args:
        shape: a :class:`~dipnet.shapes.Shape` (``volume_below``, ``radius``).
        direction: unit "up" vector ``(ndim,)``.
        tank: the tank (``A`` = ``tank.cross_section_mm2``).
        stage_mm: stage positions ``(n,)`` mm (increasing = lowered).
        t_start_mm: water line height (object frame) at stage 0 before any rise, mm.
        cavities: the shape's cavity grid (:class:`~dipnet.simulator.pockets.CavityGrid`): air trapped in its
            pockets and its dry vessels displace water too (``V + P``); ``None``: water reaches everywhere.
    """
    area = float(tank.cross_section_mm2)
    curve = dip_volume_curve(shape, np.asarray(direction, dtype=np.float64))
    trapped = None if cavities is None else cavities.curve(np.asarray(direction, dtype=np.float64))
    if trapped is not None:
        curve = CurveWithCavities(curve, trapped)
    largest = curve.max_area or 0.0  # largest cross-section seen, mm^2
    s = np.asarray(stage_mm, dtype=np.float64)
    base = t_start_mm + s
    below, section = curve.volume_and_area(base)
    lo, hi = _bracket(curve, base, area, below)
    delta = np.clip(below / (area - np.minimum(section, 0.5 * area)), lo, hi)  # one Newton step from 0
    tol = _RELATIVE_TOL * max(curve.total, 1e-300)
    for _ in range(_NEWTON_STEPS):  # safeguarded Newton on the exact V
        submerged, section = curve.volume_and_area(base + delta)
        largest = max(largest, float(section.max(initial=0.0)))
        if largest >= area:
            source = getattr(shape, "source", None)  # a mesh file's path
            what = f"mesh file {source}" if source else f"shape {getattr(shape, 'name', type(shape).__name__)!r}"
            raise ValueError(f"{what}: the object's cross-section ({largest:.0f}) is not smaller than the tank's "
                             f"free cross-section ({area:.0f}): it cannot be dipped in this tank; make it smaller "
                             "with shape.radius= (mm) or, for a mesh in its own units, shape.scale= (mm per file "
                             "unit), or dip it in a larger tank")
        g = area * delta - submerged
        if np.abs(g).max(initial=0.0) <= tol:
            break
        lo = np.where(g < 0, np.maximum(lo, delta), lo)
        hi = np.where(g > 0, np.minimum(hi, delta), hi)
        step = delta - g / (area - section)
        inside = (step >= lo) & (step <= hi)
        delta = np.where(inside, step, 0.5 * (lo + hi))
    else:
        submerged = curve.volume(base + delta)
    residual = float(np.abs(area * delta - submerged).max(initial=0.0))
    return DipState(stage_mm=s, rise_mm=delta, waterline_mm=base + delta, submerged=area * delta,
                    residual=residual, pocket_mm3=0.0 if trapped is None else trapped.pocket_volume,
                    vessel_mm3=0.0 if trapped is None else trapped.vessel_volume)


def _bracket(curve, base: np.ndarray, area: float, below: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` rises (n,) mm with ``g(lo) <= 0 <= g(hi)``, ``g(delta) = A delta - V(base + delta)``.

    For a monotone ``V`` (a closed surface) ``[V(base) / A, V_total / A]`` holds. An open
    surface's flux ``V`` may fall or overshoot its final value, so the interval is widened by
    doubling steps until the signs hold (``g`` still rises with slope ``A - a > 0``).
    """
    lo = below / area
    hi = np.full_like(lo, max(curve.total, float(below.max(initial=0.0))) / area)
    if curve.monotone:
        return lo, hi
    for doubling in range(_NEWTON_STEPS):
        g_lo, g_hi = area * lo - curve.volume(base + lo), area * hi - curve.volume(base + hi)
        if not ((g_lo > 0).any() or (g_hi < 0).any()):
            break
        # g has slope of about A: move each bad end past the root by twice (then 4x, ...) its excess
        lo = np.where(g_lo > 0, lo - 2**doubling * 2 * g_lo / area, lo)
        hi = np.where(g_hi < 0, hi - 2**doubling * 2 * g_hi / area, hi)
    return lo, hi


def _expect(name: str, value: object, cls: type) -> object:
    """``value`` if it is ``None`` or a ``cls``; else ``ValueError`` (e.g. a config node without its ``_target_``)."""
    if value is None or isinstance(value, cls):
        return value
    raise ValueError(f"the simulator's {name} must be a {cls.__name__}, got {type(value).__name__} {value!r}: in "
                     f"a config give its class, e.g. source.simulator.{name}={{_target_: "
                     f"{cls.__module__}.{cls.__name__ if cls is not SensorModel else 'LevelSensor'}, ...}}")


def _check_quantum(sensor: SensorModel, tank: Tank, volume: float) -> None:
    """Refuse a sensor whose quantum is at least the object's whole reading change (``volume`` mm^3
    over ``tank``): every reading of a dip would round to one or two levels."""
    rise = float(np.ptp(sensor.ideal(tank, np.array([0.0, volume]))))
    if sensor.quantum > 0 and sensor.quantum >= rise:
        unit = sensor.quantity.rsplit("_", 1)[-1]
        what = "its volume over the tank's section" if sensor.quantity == "level_mm" \
            else "the mass of water it displaces"
        fix = "use a smaller tank" if sensor.quantity == "level_mm" else "dip a larger object"
        raise ValueError(f"the sensor's quantum ({sensor.quantum:g} {unit}) is at least the whole change the object "
                         f"makes in its reading ({rise:.3g} {unit}, {what}): every dip would read one level; lower "
                         f"the sensor's quantum or {fix}")


def simulate_scan(shape, directions, *, tank: Tank | None = None, sensor: SensorModel | None = None,
                  protocol: DipProtocol | None = None, geometry: RigGeometry | None = None,
                  pockets: Pockets | bool | None = None, seed: int | None = None, progress: bool = True) -> RawScan:
    """Dip ``shape`` along every direction and record what the rig would: a :class:`RawScan`.

    Args:
        shape: a :class:`~dipnet.shapes.Shape` (its exact ``volume_below`` is the physics).
        directions: commanded "up" vectors ``(K, ndim)`` (torch or numpy; normalised here: a zero or
            non-finite row raises a ``ValueError`` naming it, :func:`~dipnet.core.orientations.unit_directions`).
        tank: default :meth:`Tank.default` for the shape's ``ndim``; the *nominal* tank.
        sensor: default ``LevelSensor()`` (ideal: no noise, no quantisation).
        protocol: default ``DipProtocol()`` (1 mm steps).
        geometry: the rig's true geometry (:class:`~dipnet.core.geometry.RigGeometry`), applied
            to make mismatched data: true directions from the commanded rig angles, start
            heights ``t0 + p (cos r - 1) + e sin r``, true stage travel, the true cross-section,
            level drift and sensor lag. Default: the ideal rig. The scan records what the rig
            is told (commanded angles and stage, the nominal tank, ``t_start_mm = t0``), and
            the true geometry in ``header.config["simulated_geometry"]``.
        pockets: trap air in the shape's cavities that open downward and keep those that open upward dry
            until the water reaches their rim (:class:`~dipnet.simulator.pockets.Pockets`; ``True`` its
            defaults). Default: water reaches every cavity at once, as the dip transform assumes.
        seed: noise seed (default the sensor's); orientation ``k`` uses the stream ``(seed, k)``.
        progress: show a progress bar over orientations.

    Returns:
        The raw scan in memory; every orientation is complete and its ``meta`` holds the
        ``noise_sigma`` (reading units) and the solver ``residual_mm3`` (with ``pockets`` also the volume of the
        dip's air pockets and vessels, ``pocket_mm3`` and ``vessel_mm3``). ``t0`` lies
        ``clearance_mm`` below the bounding sphere for the highest start of any dip.
    """
    dirs = unit_directions(directions, shape.ndim).detach().cpu().numpy()
    tank = _expect("tank", tank, Tank) or Tank.default(shape.ndim)
    sensor = _expect("sensor", sensor, SensorModel) or LevelSensor()
    protocol = _expect("protocol", protocol, DipProtocol) or DipProtocol()
    geometry = geometry or RigGeometry()
    seed = getattr(sensor, "seed", 0) if seed is None else seed
    radius = float(shape.radius())
    tilt, spin, true_dirs, shift = _commanded_angles(dirs, geometry)
    t0 = -(radius + protocol.clearance_mm + max(0.0, float(shift.max())))
    t_start = t0 + shift
    true_tank = replace(tank, cross_section_mm2=geometry.area(tank.cross_section_mm2))
    _check_quantum(sensor, true_tank, float(shape.volume))
    n = int(np.ceil((radius - t_start.min()) / (protocol.step_mm * geometry.step_scale) - 1e-9)) + 1 \
        + protocol.extra_steps
    check_simulation(shape, len(dirs), n, protocol.step_mm)
    pockets = as_pockets(pockets)
    cavities = None if pockets is None else CavityGrid(shape, pockets.resolution)
    stage = np.arange(n) * protocol.step_mm
    per_dip_s = n * protocol.settle_s + protocol.reorient_s
    header = ScanHeader(
        quantity=sensor.quantity, ndim=shape.ndim, tank_cross_section_mm2=float(tank.cross_section_mm2),
        step_mm=float(protocol.step_mm), t_start_mm=t0, resolution=sensor.quantum or None,
        density_g_per_mm3=getattr(sensor, "density_g_per_mm3", WATER_DENSITY_G_PER_MM3),
        rig="dipnet.simulator",
        config={"tank": asdict(tank), "sensor": sensor.to_dict(), "protocol": asdict(protocol), "seed": seed,
                "simulated_geometry": geometry.to_dict(), "pockets": None if pockets is None else asdict(pockets)},
        metadata={"shape": getattr(shape, "name", type(shape).__name__), "volume": float(shape.volume)})
    scan = RawScan(header=header)
    for k in tqdm(range(len(dirs)), desc="dipping", unit="dip", disable=not progress):
        state = solve_dip(shape, true_dirs[k], true_tank, geometry.true_stage(stage), float(t_start[k]), cavities)
        time_s = k * per_dip_s + (np.arange(n) + 1) * protocol.settle_s
        rng = np.random.default_rng([int(seed), k])
        ideal = sensor.ideal(true_tank, state.submerged)
        if sensor.quantity == "level_mm":
            ideal = geometry.apply_levels(ideal, time_s)
        values, sigma = sensor.read(ideal, time_s, rng)
        scan.orientations.append(OrientationScan(
            k=k, direction=dirs[k], tilt_deg=None if tilt is None else float(tilt[k]),
            spin_deg=None if spin is None else float(spin[k]),
            meta={"noise_sigma": sigma, "residual_mm3": state.residual,
                  **({} if cavities is None else {"pocket_mm3": state.pocket_mm3, "vessel_mm3": state.vessel_mm3})},
            stage_mm=stage, values=values, time_s=time_s, complete=True))
    return scan


def _commanded_angles(dirs: np.ndarray, geometry: RigGeometry):
    """``(tilt (K,) | None, spin (K,) | None, true directions (K, d), height shift (K,))`` for
    commanded directions ``(K, d)``; in 2D there are no rig angles (only the ideal rotary axes)."""
    if dirs.shape[1] == 3:
        tilt, spin = direction_to_rig(dirs)
        return tilt, spin, geometry.directions(tilt, spin).numpy(), geometry.height_shift(tilt)
    if geometry.tilt_zero_deg or geometry.spin_zero_deg or geometry.pivot_mm or geometry.tilt_axis_offset_mm:
        raise ValueError("rotary-axis geometry (pivot, tilt-axis offset, zero offsets) needs 3D directions")
    return None, None, dirs, np.zeros(len(dirs))
