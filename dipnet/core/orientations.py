"""Dipping orientations: unit vectors in the object frame.

A *dip direction* ``theta`` is the unit vector, expressed in the object's frame (the grid
frame, components ordered ``(x, y[, z])``), that points **up** in the tank, i.e. against the
direction of travel. The water line sits at height ``t = x . theta`` over the object, so the
parts with the smallest ``t`` go under water first and the dip profile is ordered by
increasing ``t``. Since a profile along ``-theta`` is the same profile reversed, a hemisphere
(``z >= 0`` in 3D, angles in ``[0, 180)`` degrees in 2D) holds every distinct orientation.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from dipnet.core.counts import is_real


def unit_directions(directions, ndim: int) -> torch.Tensor:
    """``directions`` (anything ``torch.as_tensor`` takes, of any length) as unit vectors ``(K, ndim)`` float64.

    Raises:
        ValueError: a shape other than ``(K, ndim)`` with ``K >= 1``, or rows holding a NaN or infinite
            component or a zero vector (the message names the rows).
    """
    if isinstance(directions, np.ndarray):  # a view with negative strides ([::-1]) is copied: torch takes none
        directions = np.ascontiguousarray(directions)
    d = torch.as_tensor(directions, dtype=torch.float64)
    if d.ndim != 2 or d.shape[1] != ndim or d.shape[0] < 1:
        raise ValueError(f"directions must have shape (K, {ndim}) with K >= 1, got {tuple(d.shape)}")
    finite = torch.isfinite(d).all(dim=1)
    if not bool(finite.all()):
        raise ValueError(f"directions contain non-finite (NaN or inf) components in rows "
                         f"{torch.nonzero(~finite).squeeze(1).tolist()}")
    norms = d.norm(dim=1, keepdim=True)
    zero = norms[:, 0] < 1e-12
    if bool(zero.any()):
        raise ValueError(f"directions contain a zero vector in rows {torch.nonzero(zero).squeeze(1).tolist()}")
    return d / norms


def angles_2d(k: int, *, start_deg: float = 0.0) -> torch.Tensor:
    """``k`` equally spaced 2D angles in ``[0, 180)`` degrees, shape ``(k,)``, degrees."""
    _check_count(k)
    return start_deg + torch.arange(k, dtype=torch.float64) * (180.0 / k)


def directions_2d(angles_deg: torch.Tensor | np.ndarray | list[float]) -> torch.Tensor:
    """Unit vectors ``(cos a, sin a)`` for angles in degrees; shape ``(k, 2)``.

    Three or more angles that all lie within ``[-2 pi, 2 pi]`` (as radians would, e.g.
    ``np.linspace(0, np.pi, k)``) are warned about: as degrees they span a few degrees only, and dips that
    close together leave the shape undetermined (give ``np.degrees(angles)``)."""
    a = torch.as_tensor(angles_deg, dtype=torch.float64)
    if a.numel() >= 3 and bool(torch.isfinite(a).all()) and float(a.abs().max()) <= 2 * math.pi \
            and float(a.max() - a.min()) > 0:
        warnings.warn(f"directions_2d: all {a.numel()} angles lie within [-2 pi, 2 pi] ({float(a.min()):.3g} to "
                      f"{float(a.max()):.3g}), which are read as degrees: the dips span {float(a.max() - a.min()):.3g} "
                      "deg; angles in radians need np.degrees(angles)", stacklevel=2)
    return _unit_2d(a)


def _unit_2d(angles_deg: torch.Tensor) -> torch.Tensor:
    """``(cos a, sin a)`` of float64 ``angles_deg`` ``(k,)`` (degrees), ``(k, 2)``."""
    a = torch.deg2rad(angles_deg)
    return torch.stack([torch.cos(a), torch.sin(a)], dim=-1)


def fibonacci_hemisphere(k: int) -> torch.Tensor:
    """``k`` nearly uniform directions on the upper hemisphere (Fibonacci lattice), ``(k, 3)``."""
    _check_count(k)
    i = torch.arange(k, dtype=torch.float64)
    z = 1.0 - (i + 0.5) / k  # uniform in (0, 1): equal-area bands of the hemisphere
    golden = math.pi * (3.0 - math.sqrt(5.0))
    phi = golden * i
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def random_hemisphere(k: int, seed: int) -> torch.Tensor:
    """``k`` directions uniform on the upper hemisphere from an explicit seed, ``(k, 3)``."""
    _check_count(k)
    gen = torch.Generator().manual_seed(int(seed))
    v = torch.randn(k, 3, generator=gen, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    return v * torch.where(v[:, 2:] < 0, -1.0, 1.0)


def paper_grid(n_theta: int, n_phi: int) -> torch.Tensor:
    """The paper's grid: polar ``theta`` in ``[0, 90)``, azimuth ``phi`` in ``[0, 360)``.

    Directions ``(sin t cos p, sin t sin p, cos t)``; shape ``(n_theta * n_phi, 3)``, theta-major.
    """
    _check_count(n_theta)
    _check_count(n_phi)
    t = torch.deg2rad(torch.arange(n_theta, dtype=torch.float64) * (90.0 / n_theta))
    p = torch.deg2rad(torch.arange(n_phi, dtype=torch.float64) * (360.0 / n_phi))
    tt, pp = torch.meshgrid(t, p, indexing="ij")
    v = torch.stack([tt.sin() * pp.cos(), tt.sin() * pp.sin(), tt.cos()], dim=-1)
    return v.reshape(-1, 3)


def rig_to_direction(tilt_deg, spin_deg) -> torch.Tensor:
    """Rig angles to dip directions in the object frame; shape ``(k, 3)``.

    The rig first *spins* the object by ``spin_deg`` about its own z axis (the axis that is
    vertical at rest), then *tilts* that axis by ``tilt_deg`` away from the vertical. The
    vertical "up" then lies at polar angle ``tilt`` from the object's z axis and at azimuth
    ``-spin`` about it: ``(sin(tilt) cos(spin), -sin(tilt) sin(spin), cos(tilt))``.
    This is the physically consistent reading of the authors' robot (R1 = tilt, R2 = spin).
    """
    t = torch.deg2rad(torch.as_tensor(tilt_deg, dtype=torch.float64)).reshape(-1)
    s = torch.deg2rad(torch.as_tensor(spin_deg, dtype=torch.float64)).reshape(-1)
    t, s = torch.broadcast_tensors(t, s)
    return torch.stack([t.sin() * s.cos(), -t.sin() * s.sin(), t.cos()], dim=-1)



def direction_to_rig(directions) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`rig_to_direction`: unit "up" vectors ``(K, 3)``
    (upper hemisphere) to ``(tilt_deg (K,), spin_deg (K,))``; spin is 0 for vertical ones."""
    d = np.asarray(torch.as_tensor(directions, dtype=torch.float64).numpy(), dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(d[:, 2], -1.0, 1.0)))
    lateral = np.hypot(d[:, 0], d[:, 1])
    spin = np.where(lateral > 1e-12, np.degrees(np.arctan2(-d[:, 1], d[:, 0])), 0.0)
    return tilt, np.mod(spin, 360.0)


def _angles(name: str, values) -> list[float]:
    """``values`` (option ``name``, degrees) as finite floats; ``ValueError`` naming the option otherwise."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__") or not list(values):
        example = "[0,25,50,70]" if name == "tilts" else "[0,180]"
        raise ValueError(f"{name} must be a non-empty list of angles (degrees), e.g. {name}={example}, got {values!r}")
    angles = []
    for value in values:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{name}={list(values)!r}: {value!r} is not a finite angle (degrees)")
        angles.append(float(value))
    return angles


def check_grid_angles(tilts, spins, max_tilt_deg: float = 90.0) -> None:
    """Raise ``ValueError`` for a grid of rig angles (degrees) the rig cannot dip: ``tilts`` and
    ``spins`` must be non-empty lists of finite angles, every tilt within ``[0, max_tilt_deg]`` (the
    rig's mechanical limit; a tilt the other way is the same tilt at spin + 180). Spins are free."""
    tilt_list = _angles("tilts", tilts)
    _angles("spins", spins)
    outside = [t for t in tilt_list if not -1e-9 <= t <= max_tilt_deg + 1e-9]
    if outside:
        hint = "; a negative tilt is the positive one at spin + 180" if min(outside) < 0 else ""
        raise ValueError(f"tilts=[{','.join(f'{t:g}' for t in tilt_list)}]: {', '.join(f'{t:g}' for t in outside)} "
                         f"deg outside the rig's tilt range [0, {max_tilt_deg:g}] deg (max_tilt_deg){hint}")


#: Rig angles closer than this (degrees, tilt and spin modulo 360) command one pose: a grid plan dips it once
#: (:func:`distinct_rig_angles`). Far below any rig's angle resolution, far above rounding.
SAME_POSE_DEG = 1e-3


def distinct_rig_angles(pairs, tol_deg: float = SAME_POSE_DEG
                        ) -> tuple[list[tuple[float, float]], list[tuple[tuple[float, float], tuple[float, float]]]]:
    """``pairs`` of rig angles ``(tilt_deg, spin_deg)`` (degrees) with every pair that commands an earlier pair's
    pose left out: the same tilt and the same spin modulo 360 deg, within ``tol_deg`` (spin 360 is spin 0).
    Pairs at tilt 0 with other spins are kept: an ideal rig dips them all along the vertical, but on a rig whose
    tilt zero is off they are different directions, and self-calibration reads the tilt zero from them.

    Returns:
        The kept pairs, in their order, and the left-out ones as ``(pair, the earlier pair it repeats)``.
    """
    kept: list[tuple[float, float]] = []
    repeats: list[tuple[tuple[float, float], tuple[float, float]]] = []
    for tilt, spin in ((float(t), float(s)) for t, s in pairs):
        same = next(((t0, s0) for t0, s0 in kept
                     if abs(tilt - t0) <= tol_deg and abs((spin - s0 + 180.0) % 360.0 - 180.0) <= tol_deg), None)
        if same is None:
            kept.append((tilt, spin))
        else:
            repeats.append(((tilt, spin), same))
    return kept, repeats


def unmeasured_band_deg(directions) -> float:
    """Half-angle (deg) of the band of directions about the horizontal plane that no dip of ``directions``
    ``(K, d)`` comes within: 90 minus the largest tilt from the vertical (last) axis (``d`` and ``-d`` give the
    same planes). 0 when some dip is horizontal."""
    d = np.asarray(torch.as_tensor(directions, dtype=torch.float64).numpy())
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.degrees(np.arcsin(np.abs(d[:, -1]).min())))


def unmeasured_wedge_deg(directions) -> tuple[float, float]:
    """2D: ``(width, start)`` (deg) of the widest wedge of line angles in ``[0, 180)`` that no dip of ``directions``
    ``(K, 2)`` lies in, from ``start`` to ``start + width`` (mod 180; ``d`` and ``-d`` are one line). ``K`` equal angles
    leave ``180 / K``; no direction of the plane is special, so the wedge may lie anywhere (the 3D rig's band about
    the horizontal, :func:`unmeasured_band_deg`, is one case)."""
    d = np.asarray(torch.as_tensor(directions, dtype=torch.float64).numpy())
    if d.ndim != 2 or d.shape[1] != 2 or len(d) < 1:
        raise ValueError(f"unmeasured_wedge_deg takes 2D directions (K, 2), got shape {d.shape}")
    angles = np.sort(np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0)
    gaps = np.diff(np.concatenate([angles, angles[:1] + 180.0]))
    widest = int(np.argmax(gaps))
    return float(gaps[widest]), float(angles[widest])


#: The named orientation sets of :func:`make_directions`.
DIRECTION_SETS = ("fibonacci", "random", "uniform")


def make_directions(kind: str, k: int, ndim: int, seed: int = 0) -> torch.Tensor:
    """Named orientation set: ``fibonacci`` | ``random`` | ``uniform`` (2D angles); ``(k, ndim)``.

    ``uniform`` is an alias: the Fibonacci hemisphere in 3D, and in 2D both are the ``k`` equal angles of
    :func:`angles_2d`. An unknown
    ``kind``, a ``k`` below 1 or an ``ndim`` other than 2 or 3 raises a ``ValueError`` (in 2D as in 3D)."""
    if kind not in DIRECTION_SETS:
        raise ValueError(f"unknown orientation set {kind!r}; choose fibonacci, random or uniform")
    if isinstance(ndim, bool) or ndim not in (2, 3):
        raise ValueError(f"orientation sets exist in 2D and 3D, not {ndim!r}D")
    _check_count(k)
    if ndim == 2:
        if kind == "random":
            gen = torch.Generator().manual_seed(int(seed))
            return _unit_2d(torch.rand(k, generator=gen, dtype=torch.float64) * 180.0)  # any span is meant
        return _unit_2d(angles_2d(k))
    if kind == "fibonacci" or kind == "uniform":
        return fibonacci_hemisphere(k)
    return random_hemisphere(k, seed)


def _check_count(k: int) -> None:
    if int(k) != k or k < 1:
        raise ValueError(f"number of orientations must be a positive integer, got {k!r}")


MAX_CANDIDATES = 100_000  # the planners score every candidate; at a 1 degree step the hemisphere holds ~21,000


def reachable_candidates(tilt_range_deg=(0.0, 90.0), spin_range_deg=(0.0, 360.0),
                         step_deg: float = 10.0) -> torch.Tensor:
    """The directions a rig can reach, on a grid of rig angles: the planners' candidate set, ``(C, 3)``.

    Tilts run from ``tilt_range_deg[0]`` to ``tilt_range_deg[1]`` and spins over ``spin_range_deg``
    (half-open when it spans a full turn) in steps of about ``step_deg`` degrees; at each tilt the
    spin step widens as ``1 / sin(tilt)`` so the candidates cover the cap evenly (one candidate at
    tilt 0). Directions come from :func:`rig_to_direction`; duplicates are removed.
    """
    t0, t1 = (float(v) for v in tilt_range_deg)
    s0, s1 = (float(v) for v in spin_range_deg)
    step = float(step_deg)
    if not 0.0 <= t0 <= t1 <= 90.0:
        raise ValueError(f"tilt range must satisfy 0 <= min <= max <= 90 degrees, got {tilt_range_deg!r}")
    if not s0 <= s1 <= s0 + 360.0:
        raise ValueError(f"spin range must satisfy min <= max <= min + 360 degrees, got {spin_range_deg!r}")
    if not 0.0 < step <= 90.0:
        raise ValueError(f"candidate step must be in (0, 90] degrees, got {step_deg!r}")
    n_tilts = max(1, math.ceil((t1 - t0) / step - 1e-9)) + 1 if t1 > t0 else 1
    tilts = np.linspace(t0, t1, n_tilts) if n_tilts <= MAX_CANDIDATES else None
    n_candidates = math.inf if tilts is None else int(np.maximum(
        1, np.ceil((s1 - s0) * np.sin(np.radians(tilts)) / step - 1e-9)).sum())
    if n_candidates > MAX_CANDIDATES:  # step_deg=0.001 built ~3e10 rig angles: the job ran out of memory, no message
        raise ValueError(f"candidate step {step_deg!r} degrees gives "
                         f"{'more than ' + format(MAX_CANDIDATES, ',') if tilts is None else format(n_candidates, ',')}"
                         f" candidate directions over tilts {t0:g}-{t1:g} and spins {s0:g}-{s1:g} degrees, at most "
                         f"{MAX_CANDIDATES:,}: give a larger step (reach.step_deg)")
    full_turn = s1 - s0 >= 360.0 - 1e-9
    pairs = []
    for tilt in tilts:
        arc = (s1 - s0) * math.sin(math.radians(tilt))  # arc length of the spin range at this tilt, degrees
        n = max(1, math.ceil(arc / step - 1e-9))
        spins = np.linspace(s0, s1, n, endpoint=False) if full_turn else np.linspace(s0, s1, n + 1 if arc > 0 else 1)
        pairs += [(tilt, spin) for spin in spins]
    tilt, spin = np.array(pairs).T
    directions = rig_to_direction(tilt, spin)
    _, keep = np.unique(np.round(directions.numpy(), 9), axis=0, return_index=True)
    return directions[np.sort(keep)]


def within_reach(directions, tilt_range_deg=(0.0, 90.0), spin_range_deg=(0.0, 360.0),
                 tol_deg: float = 1e-6) -> torch.Tensor:
    """Boolean mask ``(k,)``: which unit "up" vectors ``(k, 3)`` the rig limits allow (degrees)."""
    d = torch.as_tensor(directions, dtype=torch.float64).reshape(-1, 3)
    d = d / d.norm(dim=1, keepdim=True)
    tilt = torch.rad2deg(torch.arccos(d[:, 2].clamp(-1.0, 1.0)))
    spin = torch.rad2deg(torch.atan2(-d[:, 1], d[:, 0]))
    s0, s1 = (float(v) for v in spin_range_deg)
    rel = torch.remainder(spin - s0, 360.0)
    spin_ok = (rel <= s1 - s0 + tol_deg) | (rel >= 360.0 - tol_deg) | (tilt < tol_deg)
    return (tilt >= float(tilt_range_deg[0]) - tol_deg) & (tilt <= float(tilt_range_deg[1]) + tol_deg) & spin_ok



@dataclass(frozen=True)
class Reach:
    """The orientations a rig can reach: tilt and spin ranges (degrees) and the candidate step.

    ``tilt`` is the angle of the dip direction from the object's z axis, ``spin`` the rig's spin
    (see :func:`rig_to_direction`). The full hemisphere is ``Reach()``; the authors' robot is
    ``Reach(tilt_range_deg=(0, 35))``.
    """

    tilt_range_deg: tuple[float, float] = (0.0, 90.0)
    spin_range_deg: tuple[float, float] = (0.0, 360.0)
    step_deg: float = 10.0

    def __post_init__(self) -> None:
        """Raise ``ValueError`` naming the option unless each range is two numbers (degrees) and the step one
        (a ``true`` was read as 1 degree, ``[0, 35, 90]`` failed as "too many values to unpack"); then the limits
        are checked by :func:`reachable_candidates`."""
        for name in ("tilt_range_deg", "spin_range_deg"):
            value = getattr(self, name)
            if isinstance(value, str) or not hasattr(value, "__len__") or len(value) != 2 \
                    or not all(map(is_real, value)):
                raise ValueError(f"reach.{name} must be two numbers [min, max] (degrees), got {value!r}")
            object.__setattr__(self, name, tuple(float(v) for v in value))
        if not is_real(self.step_deg):
            raise ValueError(f"reach.step_deg must be a number of degrees, got {self.step_deg!r}")
        try:
            reachable_candidates(self.tilt_range_deg, self.spin_range_deg, self.step_deg)  # validates
        except ValueError as exc:  # was "candidate step must be ...", naming no option
            raise ValueError(f"reach (tilt_range_deg, spin_range_deg, step_deg): {exc}") from None

    def ranges(self) -> str:
        """The tilt and spin ranges as a message names them: ``"tilt 0-35 deg, spin 0-360 deg"``."""
        (t0, t1), (s0, s1) = self.tilt_range_deg, self.spin_range_deg
        return f"tilt {t0:g}-{t1:g} deg, spin {s0:g}-{s1:g} deg"

    def candidates(self) -> torch.Tensor:
        """The candidate directions ``(C, 3)`` (:func:`reachable_candidates`)."""
        return reachable_candidates(self.tilt_range_deg, self.spin_range_deg, self.step_deg)

    def contains(self, directions) -> torch.Tensor:
        """Boolean mask ``(k,)`` of the directions ``(k, 3)`` within reach (:func:`within_reach`)."""
        return within_reach(directions, self.tilt_range_deg, self.spin_range_deg)

    def uniform(self, k: int) -> torch.Tensor:
        """``k`` nearly uniform reachable directions ``(k, 3)``: a Fibonacci lattice over equal-area
        bands of the reachable tilts, its azimuths spread over the spin range (the baseline plan)."""
        _check_count(k)
        z_hi, z_lo = (math.cos(math.radians(t)) for t in self.tilt_range_deg)
        i = torch.arange(k, dtype=torch.float64)
        tilt = torch.rad2deg(torch.arccos(z_hi - (i + 0.5) / k * (z_hi - z_lo)))
        s0, s1 = self.spin_range_deg
        spin = s0 + (s1 - s0) * torch.remainder(i * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)
        return rig_to_direction(tilt, spin)
