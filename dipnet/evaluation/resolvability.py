"""What a dipping plan can and cannot resolve: its missing cone and its frequency coverage.

A dip along the unit direction ``theta`` integrates the occupancy over planes normal to
``theta``; by the Fourier-slice theorem its profile gives the object's 3D spectrum on the
line ``k = s theta`` (``theta`` and ``-theta`` give the same line). A plan of ``K``
directions therefore samples ``K`` lines through the origin of frequency space, and:

* the **missing cone** is the set of plane normals (equally: frequency directions) far from
  every measured direction. ``missing_cone_deg`` is the largest angular distance from any
  direction on the sphere to its nearest measured direction (the half-angle of the largest
  uncovered cap; 90 deg when a whole great circle of directions is unseen);
* a frequency ``k`` (cycles/mm) at angle ``alpha`` from its nearest sampled line is
  **covered** when ``|k| sin(alpha) <= 1 / D``, with ``D`` the object's diameter (mm): an
  object of size ``D`` has a spectrum smooth on the scale ``1 / D`` (Crowther's criterion),
  so a line informs the frequencies within that distance. ``frequency_coverage`` is the
  covered share of the frequency ball up to the grid's Nyquist frequency;
  ``polar_coverage`` / ``azimuthal_coverage`` restrict it to frequency directions within
  30 deg of the grid's vertical axis (structure along z: the heights of features) / of the
  horizontal plane (structure across z: the azimuthal arrangement of features).

Directions near the pole (small tilts, as on the authors' robot) cover the polar frequencies
and leave the horizontal ones unmeasured: no spin of a near-vertical object changes that.
With a measurement, :func:`ring_variation` also checks the data themselves: how much the
profiles of one tilt change with the spin, against the noise (``azimuthal_signal_ratio``).

The map is per frequency, not per voxel: plane integrals along parallel planes are
shift-invariant, so every voxel of the working ball sees the same covered frequencies (a
per-voxel ``diag(A^T A)`` is flat up to partial-volume ripple: 1.9% rms over the working
ball for the cats plan at 24^3). Everything here is geometry: no operator is applied, so it
costs about 0.1 s at 40^3.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dipnet.core.warn import log_and_warn
from dipnet.evaluation.consistency import estimate_slab_sigma
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import (direction_to_rig, fibonacci_hemisphere, unmeasured_band_deg,
                                      unmeasured_wedge_deg)

SPHERE_SAMPLES = 20_000  # directions on which the missing cone is evaluated (3D)
BAND_DEG = 30.0  # polar / azimuthal frequency bands: within this angle of the axis / plane
#: Half-angle (deg) of the band about the horizontal plane that no dip reaches above which a job warns
#: (:func:`warn_unmeasured_band`): where self-calibration calls a scan's missing cone wide (its
#: ``MISSING_CONE_DEG``, :mod:`dipnet.calibration.self_calibration`) and lets the shape prior decide the volume.
UNMEASURED_BAND_DEG = 10.0
#: A 3D plan leaving some direction of the hemisphere more than this (deg) from every dip is too sparse to determine
#: a shape however evenly it is spread (:func:`warn_unmeasured_band`): 6 or fewer Fibonacci dips (4: 55.9 deg, 6: 47.6,
#: 8: 41.4). ``solver=voxel`` at 24^3 from 4 dips: IoU 0.56 (fish), 0.66 (bunny), ``consistent`` without a word.
SPARSE_CONE_DEG = 45.0
#: Two dips whose lines lie closer than this (deg) are one line (:func:`distinct_lines`): a repeated dip averages the
#: noise but measures no new direction.
SAME_LINE_DEG = 1.0

log = logging.getLogger(__name__)


@dataclass
class Resolvability:
    """Coverage of a plan (see the module docstring). Angles in degrees, frequencies in cycles/mm.

    Attributes:
        directions: the plan's unit directions ``(K, d)``.
        sphere: sample directions of the hemisphere ``(S, d)`` and ``gap_deg`` ``(S,)``: their
            angle to the nearest plan direction.
        missing_cone_deg: ``gap_deg.max()``; ``mean_gap_deg``: its mean over the hemisphere.
        uncovered_direction: the sphere sample farthest from the plan ``(d,)``.
        coverage: covered frequencies on the grid's FFT lattice, ``grid.shape`` (bool,
            ``numpy.fft.fftfreq`` order along each axis ``[z, y, x]``).
        polar_deg, coverage_by_polar: covered share of the frequency ball per frequency polar
            angle (angle of ``k`` from the vertical axis), ``(B,)`` each.
        frequency_coverage, polar_coverage, azimuthal_coverage: covered shares (0..1).
        diameter_mm: the object size ``D`` used by the coverage criterion.
        ring_polar_deg, ring_rms: per ring of measured directions at one polar angle (with at
            least two azimuths), the rms deviation of its profiles from the ring's mean (mm^3);
            empty without a measurement.
        azimuthal_signal_ratio: the largest ``ring_rms`` over the noise sigma estimated from the
            profiles (:func:`dipnet.evaluation.consistency.estimate_slab_sigma`): about 1 when turning the
            object about its axis (the rig's spin) changes nothing beyond noise; ``None``
            without rings (and in 2D, which has no spin).
    """

    directions: np.ndarray
    sphere: np.ndarray
    gap_deg: np.ndarray
    missing_cone_deg: float
    mean_gap_deg: float
    uncovered_direction: np.ndarray
    coverage: np.ndarray
    polar_deg: np.ndarray
    coverage_by_polar: np.ndarray
    frequency_coverage: float
    polar_coverage: float
    azimuthal_coverage: float
    diameter_mm: float
    ring_polar_deg: np.ndarray
    ring_rms: np.ndarray
    azimuthal_signal_ratio: float | None

    def metrics(self) -> dict:
        """Summary numbers for ``metrics.json``."""
        return {"missing_cone_deg": self.missing_cone_deg, "mean_direction_gap_deg": self.mean_gap_deg,
                "frequency_coverage": self.frequency_coverage, "polar_coverage": self.polar_coverage,
                "azimuthal_coverage": self.azimuthal_coverage, "resolvability_diameter_mm": self.diameter_mm,
                "azimuthal_signal_ratio": self.azimuthal_signal_ratio}

    def save(self, path: str | Path) -> Path:
        """Write every array and number to an ``.npz`` file; returns the path."""
        path = Path(path)
        np.savez_compressed(path, directions=self.directions, sphere=self.sphere, gap_deg=self.gap_deg,
                            uncovered_direction=self.uncovered_direction, coverage=self.coverage,
                            polar_deg=self.polar_deg, coverage_by_polar=self.coverage_by_polar,
                            ring_polar_deg=self.ring_polar_deg, ring_rms=self.ring_rms,
                            **{k: np.float64(np.nan if v is None else v) for k, v in self.metrics().items()})
        return path


def hemisphere_samples(ndim: int, n: int = SPHERE_SAMPLES) -> np.ndarray:
    """Nearly uniform unit directions of the upper half-space, ``(n, ndim)`` (2D: angles in
    [0, 180) degrees)."""
    if ndim == 3:
        return fibonacci_hemisphere(n).numpy()
    a = np.pi * (np.arange(n) + 0.5) / n
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def angle_to_plan(points: np.ndarray, directions: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Angle (radians) from each unit vector ``points`` ``(P, d)`` to the nearest line
    ``+-directions`` ``(K, d)``; ``(P,)``."""
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        cos = np.abs(points[i:i + chunk] @ directions.T).max(axis=1)
        out[i:i + chunk] = np.arccos(np.clip(cos, 0.0, 1.0))
    return out


def warn_unmeasured_band(directions, limit_deg: float = UNMEASURED_BAND_DEG) -> str | None:
    """Log and ``warnings.warn`` how wide the band no dip of ``directions`` ``(K, d)`` reaches is, when it is wider
    than ``limit_deg`` (:func:`~dipnet.core.orientations.unmeasured_band_deg`); returns the message, or ``None``. A
    property of the plan, not a failed check of the result: surfaces whose normals lie in the band are the priors'
    guess.

    2D dips ``(K, 2)`` have no rig and no special direction: the widest wedge of angles between their lines
    (:func:`~dipnet.core.orientations.unmeasured_wedge_deg`) is warned wherever it lies, when its half-angle exceeds
    ``limit_deg`` and twice an even spread's (``90 / K``): equal angles are never warned. In 3D a gap elsewhere than
    about the horizontal plane (a rig whose spin turns 60 deg: 41 dips leave directions 65 deg from any dip, where
    41 spread over the hemisphere leave 18; IoU 0.80 against 0.97, ``consistent``, no word) is warned the same way
    (:func:`_cone_message`)."""
    d = torch.as_tensor(directions, dtype=torch.float64)
    message = _wedge_message(d, limit_deg) if d.ndim == 2 and d.shape[1] == 2 else \
        (_band_message(d, limit_deg) or _cone_message(d, limit_deg))
    if message is not None:
        log_and_warn(log, message, stacklevel=2)
    return message


def even_gap_deg(k: int, ndim: int) -> float:
    """The largest angle (deg) from any direction to the nearest of ``k`` dips spread evenly: 2D ``90 / k`` (equal
    angles), 3D over the Fibonacci hemisphere (:func:`~dipnet.core.orientations.fibonacci_hemisphere`: 1 and 2 dips
    90, 3 67.4, 4 55.9, 6 47.6, 7 43.1, 8 41.4, 41 18.0)."""
    if ndim == 2:
        return 90.0 / k
    return float(np.degrees(angle_to_plan(hemisphere_samples(3), fibonacci_hemisphere(k).numpy())).max())


@functools.cache
def determining_lines(ndim: int) -> int:
    """The fewest dip lines that, spread evenly, leave every direction within :data:`SPARSE_CONE_DEG` of a dip
    (:func:`even_gap_deg`: 3D 7, 2D 3)."""
    return next(k for k in itertools.count(1) if even_gap_deg(k, ndim) < SPARSE_CONE_DEG)


def distinct_lines(directions, stop_at: int | None = None) -> int:
    """How many dip lines ``directions`` ``(K, d)`` hold, ``d`` and ``-d`` one line and lines closer than
    :data:`SAME_LINE_DEG` merged (greedily, in the given order); counting stops at ``stop_at`` lines."""
    d = torch.as_tensor(directions, dtype=torch.float64).numpy()
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    kept = d[:0]
    cos_same = math.cos(math.radians(SAME_LINE_DEG))
    for direction in d:
        if len(kept) == stop_at:
            break
        if not len(kept) or np.abs(kept @ direction).max() < cos_same:
            kept = np.vstack([kept, direction])
    return len(kept)


def underdetermined_plan(directions) -> str | None:
    """Why the dips ``directions`` ``(K, d)`` cannot determine a shape, or ``None`` when they may: fewer distinct
    lines (:func:`distinct_lines`) than leave every direction within :data:`SPARSE_CONE_DEG` of a dip when spread
    evenly (:func:`even_gap_deg`: 3D 6 or fewer, 2D 2 or fewer). Whatever shape fits so few profiles passes the
    residual check, so :func:`~dipnet.evaluation.consistency.check_consistency` calls such a result
    ``underdetermined``, not ``consistent`` (a single dip: every shape with the same profile fits it)."""
    d = torch.as_tensor(directions, dtype=torch.float64)
    ndim = int(d.shape[1])
    needed = determining_lines(ndim)
    lines = distinct_lines(d, stop_at=needed)  # counting past what is needed would not change the answer
    if lines >= needed:
        return None
    gap = even_gap_deg(lines, ndim)
    dips = f"the {len(d)} dips hold {lines} distinct direction{'s' if lines > 1 else ''}" if lines < len(d) else \
        f"the {len(d)} dip{'s' if len(d) > 1 else ''}"
    return (f"{dips}: so few that even spread they leave some direction {gap:.0f} deg from every dip, so they do not "
            f"determine the shape: any shape with these profiles fits them, so a result that fits them is the "
            f"priors' guess and its verdict underdetermined, not consistent; dip along {needed} or more directions "
            f"spread over the {'half-circle' if ndim == 2 else 'hemisphere'}")


def _band_message(directions: torch.Tensor, limit_deg: float) -> str | None:
    """:func:`warn_unmeasured_band`'s message for 3D ``directions`` ``(K, 3)``, or ``None``."""
    band = unmeasured_band_deg(directions)
    if not band > limit_deg:
        return None
    return (f"no dip is tilted more than {90 - band:.0f} deg from the vertical: directions within {band:.0f} deg "
            f"of the horizontal plane are unmeasured (a missing cone), so surfaces facing them (normals within "
            f"{band:.0f} deg of horizontal: the sides) are guessed by the priors, not measured; dip at larger tilts "
            f"to narrow it")


def _cone_message(directions: torch.Tensor, limit_deg: float) -> str | None:
    """:func:`warn_unmeasured_band`'s message for 3D ``directions`` ``(K, 3)`` that leave some direction of the
    hemisphere more than ``limit_deg`` and twice as far from every dip as ``K`` dips spread over it do
    (:func:`~dipnet.core.orientations.fibonacci_hemisphere`), or ``None``."""
    d = directions.numpy()
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    sphere = hemisphere_samples(3)
    gap = np.degrees(angle_to_plan(sphere, d))
    even = even_gap_deg(len(d), 3)
    cone = float(gap.max())
    if not (cone > limit_deg and cone > 2 * even):
        if not cone > SPARSE_CONE_DEG:
            return None
        return (f"the {len(d)} dips leave directions up to {cone:.0f} deg from every dip, even spread as they are: so "
                "few dips do not determine the shape, and most of its surfaces are the priors' guess, which the "
                "consistency check cannot judge (solver=voxel at 25^3 on the fish from 4 dips: IoU 0.57 against 0.94 "
                "from 60, consistent); add dips (8 or more leave under 42 deg)")
    tilt, spin = direction_to_rig(sphere[int(gap.argmax())][None])
    return (f"the {len(d)} dips leave directions up to {cone:.0f} deg from every dip (about tilt {tilt[0]:.0f} deg, "
            f"spin {spin[0]:.0f} deg), where {len(d)} dips spread over the hemisphere leave {even:.0f}: "
            "surfaces facing "
            "them are guessed by the priors, not measured; dip there (a wider reach, or orientations spread over it)")


def _wedge_message(directions: torch.Tensor, limit_deg: float) -> str | None:
    """:func:`warn_unmeasured_band`'s message for 2D ``directions`` ``(K, 2)``, or ``None``."""
    width, start = unmeasured_wedge_deg(directions)
    even = 180.0 / len(directions)
    if not (width / 2 > limit_deg and width > 2 * even):
        return None
    return (f"the {len(directions)} dips leave the line angles from {start:.0f} to {(start + width):.0f} deg "
            f"(mod 180) undipped, a wedge of {width:.0f} deg where equally spaced dips leave {even:.0f}: surfaces "
            f"facing it (normals within {width / 2:.0f} deg of {(start + width / 2) % 180:.0f} deg) are guessed by "
            f"the priors, not measured; dip at angles within it (orientations=uniform spreads them evenly)")


def object_diameter(measurement: DipMeasurement, rel_tol: float = 0.005) -> float:
    """The median over orientations of the extent (mm) between the first and last slab holding
    more than ``rel_tol`` of the profile's largest slab (the median ignores noisy tails)."""
    p = measurement.profiles.numpy()
    full = p > rel_tol * p.max(axis=1, keepdims=True)
    if not full.any():
        raise ValueError("the measurement's profiles are all empty")
    first = full.argmax(axis=1)
    last = full.shape[1] - 1 - full[:, ::-1].argmax(axis=1)
    return float(np.median(((last - first + 1) * measurement.slab_thickness)[full.any(axis=1)]))


def resolvability(directions, grid: Grid, measurement: DipMeasurement | None = None,
                  diameter_mm: float | None = None, n_bins: int = 18) -> Resolvability:
    """Missing cone and frequency coverage of the plan ``directions`` ``(K, d)`` on ``grid``.

    Args:
        directions: unit (or any non-zero) dip directions, ``(K, grid.ndim)``.
        grid: the reconstruction grid (its FFT lattice is the frequency set; Nyquist 1 / (2 voxel)).
        measurement: optional; gives the object diameter (:func:`object_diameter`).
        diameter_mm: the object size ``D`` (default: from the measurement, else the working
            ball's diameter).
        n_bins: bins of the frequency polar angle over [0, 90] degrees.
    """
    d = np.asarray(torch.as_tensor(directions, dtype=torch.float64).numpy(), dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != grid.ndim or len(d) < 1:
        raise ValueError(f"directions must have shape (K, {grid.ndim}), got {d.shape}")
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    if (norms < 1e-12).any():
        raise ValueError("directions contain a zero vector")
    d = d / norms
    if diameter_mm is None:
        diameter_mm = object_diameter(measurement) if measurement is not None else 2 * grid.radius
    if not diameter_mm > 0:
        raise ValueError(f"the object diameter must be positive, got {diameter_mm}")

    sphere = hemisphere_samples(grid.ndim)
    gap = np.degrees(angle_to_plan(sphere, d))

    freqs = np.fft.fftfreq(grid.n, d=grid.voxel_size)  # cycles/mm
    k = np.stack(np.meshgrid(*([freqs] * grid.ndim), indexing="ij")[::-1], axis=-1).reshape(-1, grid.ndim)
    radius = np.linalg.norm(k, axis=1)
    nonzero = radius > 0
    unit = np.zeros_like(k)
    unit[nonzero] = k[nonzero] / radius[nonzero, None]
    alpha = np.zeros(len(k))
    alpha[nonzero] = angle_to_plan(unit[nonzero], d)
    covered = radius * np.sin(alpha) <= 1.0 / diameter_mm
    inside = radius <= 0.5 / grid.voxel_size  # the frequency ball up to Nyquist
    polar = np.degrees(np.arccos(np.clip(np.abs(unit[:, -1]), 0.0, 1.0)))  # angle from the vertical axis
    polar[~nonzero] = 0.0
    edges = np.linspace(0.0, 90.0, n_bins + 1)
    by_polar = np.array([_share(covered, inside & (polar >= lo) & (polar <= hi)) for lo, hi in zip(edges, edges[1:])])
    return Resolvability(
        directions=d, sphere=sphere, gap_deg=gap, missing_cone_deg=float(gap.max()), mean_gap_deg=float(gap.mean()),
        uncovered_direction=sphere[int(gap.argmax())], coverage=covered.reshape(grid.shape),
        polar_deg=0.5 * (edges[1:] + edges[:-1]), coverage_by_polar=by_polar,
        frequency_coverage=_share(covered, inside), polar_coverage=_share(covered, inside & (polar <= BAND_DEG)),
        azimuthal_coverage=_share(covered, inside & (polar >= 90.0 - BAND_DEG)), diameter_mm=float(diameter_mm),
        **_rings(measurement))


def ring_variation(measurement: DipMeasurement, tol_deg: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``(polar_deg (R,), rms (R,))``: for every ring of directions at one polar angle (within
    ``tol_deg``, angle from the last axis) holding at least two distinct directions, the rms
    deviation (mm^3) of its profiles from their mean. Directions repeated within ``tol_deg``
    are one azimuth."""
    d = measurement.directions.numpy()
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    polar = np.degrees(np.arccos(np.clip(np.abs(d[:, -1]), 0.0, 1.0)))
    key = np.round(polar / tol_deg).astype(int)
    profiles = measurement.profiles.numpy()
    angles, rms = [], []
    for k in np.unique(key):
        ring = np.flatnonzero(key == k)
        if np.degrees(angle_to_plan(d[ring], d[ring[:1]])).max() <= tol_deg:
            continue  # a single azimuth (repeats of one direction)
        dev = profiles[ring] - profiles[ring].mean(axis=0)
        angles.append(float(polar[ring].mean()))
        rms.append(float(np.sqrt((dev**2).mean())))
    return np.asarray(angles), np.asarray(rms)


def _rings(measurement: DipMeasurement | None) -> dict:
    """The ring fields of :class:`Resolvability` for ``measurement`` (empty without one, and in 2D: a 2D dip has no
    spin, and two directions at one angle from the last axis are mirror images, ``a`` and ``180 - a`` deg, whose
    profiles differ for any object but a symmetric one)."""
    if measurement is None or measurement.ndim != 3:
        return {"ring_polar_deg": np.zeros(0), "ring_rms": np.zeros(0), "azimuthal_signal_ratio": None}
    angles, rms = ring_variation(measurement)
    sigma = estimate_slab_sigma(measurement.profiles)
    ratio = float(rms.max() / sigma) if rms.size and sigma > 0 else None
    return {"ring_polar_deg": angles, "ring_rms": rms, "azimuthal_signal_ratio": ratio}


def _share(covered: np.ndarray, where: np.ndarray) -> float:
    """Covered fraction of the frequencies in ``where`` (NaN when none)."""
    return float(covered[where].mean()) if where.any() else math.nan
