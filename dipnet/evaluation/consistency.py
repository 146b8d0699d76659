"""Does a reconstruction explain its own data? Residual, volume and the noise that explains them.

For a measurement ``g`` (``(K, M)`` slab volumes on the operator's slabs, mm^3), the dip
operator ``A`` and a reconstruction ``x`` (its binary shape and its continuous occupancy):

* ``profile_residual`` = ``||A x_binary - g|| / ||g||`` and ``profile_residual_continuous``
  (same for the occupancy): 0 for a shape that reproduces every slab volume;
* ``profile_residual_expected``: what the noise alone explains, ``||n|| / ||g||`` with
  ``||n|| = sqrt(sum sigma^2)`` from the measurement's per-slab ``sigma`` when it has one, else
  from a per-slab sigma estimated (:func:`estimated_slab_noise`: the smaller of the profiles' own estimate,
  :func:`~dipnet.core.measurement.estimate_slab_sigma`, and ``sqrt(2)`` times the noise of one reading when
  the readings were recorded; ``noise_source`` says which: ``sigma``, ``readings`` or ``estimated``);
* ``volume_ratio`` = reconstructed (binary) volume / measured volume, the measured volume
  being a robust mean (:func:`~dipnet.core.measurement.robust_volume`) of every profile's total, with
  ``volume_ratio_noise`` the relative spread of that mean.

* ``hull_fill``: the measured volume over the volume of the region the dips bound (the data's
  :func:`~dipnet.solvers.optimize.support_hull` without slack, found from where each profile is
  non-empty, whatever its values). Real objects fill 4.4-76 % of it (the 16 bundled meshes at 24^3
  and 48^3, 8 to 123 dips: the hammer lowest, at 24^3 with 8 dips); a volume in a unit ten times too
  small (levels in cm under a column that says mm) fills a tenth of what it should, which the
  residual cannot show (a shape ten times thinner explains such data). Below ``hull_fill_min`` it is
  named; a compact object's tenfold error (a true fill above 40 %) stays above it, and only the
  volume ratio of a thresholded shape may show it.
* ``height_trend_pivot_mm``, ``height_trend_offset_mm``: what a wrong rig geometry leaves in
  the data whatever the reconstruction (:func:`height_trend`): every dip's centroid must be
  ``c . theta`` for one object centroid ``c``; a trend of the centroids with the tilt ``r`` as
  ``a (cos r - 1) + b sin r`` is the signature of a pivot missing from the rig's geometry by
  ``-a`` and a tilt-axis offset missing by ``-b`` (mm), which the two fields hold.
* ``profile_floor_mm3``, ``profile_floor_share``: what every dip holds where it should hold nothing
  (:func:`profile_floor`): the median over the dips of each profile's second-smallest slab volume, and
  that floor times the number of slabs over the measured volume. A dip's slabs before the object
  touches the water and after it is under are empty; a level that drifts in time (a sensor's drift,
  a leak, an inflow) adds the same volume to every slab, a floor the reconstruction then explains
  as more object (a drift of 0.01 mm/s nearly doubled a shape's volume while its residual passed).
* ``outside_share``: the largest share of a dip's volume that preprocessing found beyond the slabs (below
  the first edge, above the last: the measurement's ``outside_share`` metadata), which the profiles leave
  out (:func:`beyond_slabs`). An object reaching beyond the grid does this, and fills the dip's slabs to
  their ends, a floor the drift check would read as a drift; a drift puts as much volume per mm of
  readings outside the slabs as it puts under them, so a share that the floor explains so is set to 0.
  It joins ``grid_volume_fraction`` (the share of the dips' volume the operator's slabs hold).
* ``object_reach_mm``, ``working_radius_mm``: how far from the grid's centre the dips show the object reaching
  (:func:`~dipnet.preprocessing.validation.object_reach`, from the readings or the non-empty slabs) and the
  working ball's radius. No voxel beyond the ball can hold the object's parts there, while the slabs, which
  reach half a voxel or more past it, may hold nearly all its volume (a torus reaching 8 % beyond: 99.9 %), so
  the "beyond the slabs" share does not show it. Validation refuses such a measurement before any solver runs;
  called on its own, this check names it (and the full end slabs are not blamed on a drift).
* ``quantum_volume_mm3``, ``mean_slab_mm3``: the volume of one step of the sensor's reading, when the
  measurement records it (:mod:`dipnet.evaluation.quantisation`), and the mean slab the object fills.
  The rounding's error joins the noise of the residual (when ``sigma`` is estimated), of the
  volume ratio and of the height trend; a quantum of half a mean slab or more is named as the cause,
  and the height-trend and hull-fill checks, whose misfits it alone makes, are skipped.
* ``level_fall_share``, ``level_fall_sigmas``: a level that falls instead (a leak, evaporation, a
  sensor drifting down) leaves no floor, since preprocessing's monotone fit flattens it, and every
  profile loses volume alike; the readings after the object is under fall instead of staying put
  (:mod:`dipnet.preprocessing.level_trend`, from the measurement's ``tail_slope`` metadata): the share
  of the measured volume such a fall takes over a dip, and its standard errors (NaN without the metadata).
* ``level_drop_share``, ``level_drop_dips``: while the object goes down the level only rises, unless water
  pours into a cavity that stayed dry until the water reached its rim (a vessel, the paper's "cap";
  :mod:`dipnet.simulator.pockets` simulates it): the largest such fall of any dip's readings that lasts
  (preprocessing's ``level_drop`` metadata, :func:`~dipnet.preprocessing.level_trend.level_drop`), as a share of
  the measured volume, and how many dips show one (NaN and 0 without the metadata). The built-in chamber box,
  whose chamber opens through one channel, falls in 96 of the default job's 120 dips, by up to 10.5 %; no bundled
  mesh showed one in ``scripts/bench_pockets.py`` (docs/benchmarks/pockets.md).
* ``excess_total_share``, ``excess_total_dips``: air trapped in a cavity that opens downward leaves no trace
  within a dip, but the dip measures more than the object (:func:`excess_totals`): how far the largest profile
  total exceeds the median one, and how many dips exceed it beyond ``EXCESS_SIGMAS`` of their noise and
  ``EXCESS_TOTAL_TOL`` of the volume.
* ``reading_noise_mm3``, ``reading_noise_ratio``: the noise of one reading (as a volume) that the readings
  themselves show, and the stated noise over it (preprocessing's ``reading_noise_volume`` and
  ``reading_noise_ratio`` metadata, :func:`~dipnet.preprocessing.validation.reading_noise`; NaN without raw
  readings, the ratio also without a stated noise). A stated noise (the sensor's ``noise_sigma`` or SNR) too
  large sets the solvers' prior weights too large (an over-smoothed shape) and the residual limit too
  generous, so the residual check passes what it should not: above ``NOISE_RATIO_MAX`` it is named. On
  correct simulations with 1 mm steps (the 16 bundled meshes at 32^3 and 64^3, 41 and 123 dips, slabs of
  0.78-3.1 mm, 10-40 dB or noise-free with a reading quantum; a balance: 0.82-1.15) the ratio lies in
  0.86-1.30, so a factor 3 leaves a margin of 2.3 and flags a 5-fold overstatement. Coarser steps and cleaner
  readings let the rise's own curvature into the estimate and lower the ratio (0.46 at 40 dB with 3 mm
  steps), which only makes that check more lenient. A stated noise too small sets the prior weights too
  small (noise reconstructed as shape: the bunny at 20 dB, its noise stated 5 times too small, IoU 0.861 ->
  0.803, `consistent`): below ``1 / NOISE_RATIO_MAX`` it is named, but only when ``reading_noise_leak``
  (:func:`~dipnet.preprocessing.validation.reading_noise_leak`: the estimate from every other reading over
  the estimate from every reading) is below ``NOISE_LEAK_MAX``, so that the readings' estimate holds their
  noise alone. On five bundled meshes and the built-in box at 0.5-5 mm steps and 10-60 dB, a correct statement with a
  leak below 2 had a ratio of 0.70-1.0, and every ratio below 0.5 came with a leak of 2.5 or more.
* ``dip_outliers``, ``dip_outlier_share``, ``dip_outlier_sigmas``, ``dip_outlier_order``: the dips whose profiles
  no object shares with the other dips (:mod:`dipnet.preprocessing.dip_agreement`: each dip's central moments of
  orders 2-4 against the polynomials the others fit), and the largest one's miss in the object's scale and in noise
  sigmas. A direction filed under the wrong dip (two rows swapped, an orientation log one dip off) or an object that
  moved in its holder mid-scan does this, and an optimising solver absorbs it: three swapped pairs of the built-in
  chamber box's 40 dips gave IoU 0.74 where the right directions gave 0.97, with a smaller residual, ``consistent``.
  ``dip_agreement_tested``: how many dips the test judged; 0 when it could not run (2D dips, symmetry images, fewer
  than 13 whole dips), so "no outlier" is told from "not tested".
* ``threshold_change_depth``: why a binary shape misses data its occupancy explains
  (:func:`threshold_change_depth`). Thresholding a shape's partial-volume occupancy changes only the voxels its
  surface and its thin parts cross, a layer about one voxel thick, and a finer grid shrinks that change; a field
  smeared over thick regions (too few dips for a solver without priors, a solve that stopped short of a shape) is
  changed deep inside them too, and more resolution does not help it. The share of the change deeper than one voxel
  was at most 0.004 for the true partial-volume occupancies of the built-in chamber box and ten bundled meshes at 16^3
  and 24^3 (and 0 for the voxel and implicit solvers' hammer, thinner than a voxel), 0.14-0.42 for min-norm with 12
  dips and 0.66-0.68 for empty solves (docs/guide/bad-data.md, "The threshold's blame"). Above
  ``SMEAR_DEPTH_MAX``, or when the binary shape holds more than ``THRESHOLD_GAIN_MAX`` times the occupancy's volume
  (a threshold of 0.5 at most doubles a partial voxel; min-norm's ringing field of the hammer, thresholded by Otsu at
  0.01-0.11: 3-50 times), the hint names the occupancy as smeared instead of blaming the voxel size.
* ``symmetry_misfit``, ``symmetry_misfit_p``, ``symmetry_misfit_order``, ``symmetry_declared``,
  ``symmetry_rejected``: a symmetry the result assumed (the images of the top-level ``symmetry`` option:
  ``"images"``; a solver's symmetry prior or built-in symmetry: ``"prior"``) tested against the dips' moments
  (:mod:`dipnet.preprocessing.symmetry_moments`): a declaration the object lacks makes the shape symmetric
  whatever the dips say, and the residual need not show it (the 2D elephant under a mirror prior: residual 0.121
  under its limit 0.142, IoU 0.939 -> 0.790). Rejected when the misfit exceeds ``symmetry_misfit_limit`` with
  ``p`` below :data:`~dipnet.preprocessing.symmetry_moments.P_LIMIT`.

The verdict is ``"consistent"`` unless the residual exceeds what the noise explains times a factor (1.25 for
a stated noise, ``RESIDUAL_FACTOR`` for an estimated one) in quadrature with the grid's own error (the
discretisation floor ``residual_floor``, raised on coarse grids: :func:`residual_limit`), the volume ratio or the grid's
share of the volume is further from 1 than ``volume_tol`` (or 3 noise spreads, whichever is larger), a
dip holds more than :data:`~dipnet.core.measurement.BEYOND_SLABS_TOL` of its volume (and 3 noise sigmas)
beyond the slabs or reaches beyond the working ball (and then the profile floor is not blamed on a drift), the hull
fill is below ``hull_fill_min`` or above ``HULL_FILL_MAX`` (or the dips bound no region at all), the
height trend exceeds half a slab and 3 of its standard errors, the profile floor exceeds ``FLOOR_SIGMAS``
noise sigmas (or its standard errors, when the dips' floors agree: :func:`floor_limit`) and carries more
than ``volume_tol`` of the measured volume, or the level
falls by more than ``volume_tol`` of it over a dip, ``FLOOR_SIGMAS`` standard errors below 0, the stated
noise exceeds ``NOISE_RATIO_MAX`` times the readings' own or the binary shape's residual is under
``RESIDUAL_NOISE_SHARE_MIN`` of what the stated noise explains, at most 1 (an overstated noise, without readings
too; the empty shape leaves all of the profiles, 1, so a noise said to explain more is measured against that), some
dips disagree with the others, a dip's level falls by more than ``LEVEL_DROP_TOL`` of the volume while the object
goes down, a dip measures more than the median dip beyond its noise and ``EXCESS_TOTAL_TOL`` of the volume, or the
dips reject a declared symmetry. Each failed check is logged and raised as a :class:`DataConsistencyWarning`
(``warnings.warn``), so a result that does not explain its data never passes silently.

A result that passes every check is still ``"underdetermined"``, not ``"consistent"``, when its dips are too few to
determine any shape (``underdetermined`` holds why: :func:`~dipnet.evaluation.resolvability.underdetermined_plan`,
3D 6 or fewer distinct directions, 2D 2 or fewer): a single dip is fitted by every shape with its profile, so fitting
it proves nothing (`solver=voxel` at 24^3 from 4 dips: the fish's IoU 0.56, passing every check).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.ndimage
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import (BEYOND_SLABS_TOL, DipMeasurement, estimate_slab_sigma, reading_slab_sigma,
                                     robust_volume)
from dipnet.core.warn import log_and_warn
from dipnet.operators.base import DipOperator
from dipnet.core.reconstruction import Reconstruction
from dipnet.evaluation.quantisation import (COARSE_SHARE, Quantum, centroid_allowance, coarse_quantum_message,
                                            object_slabs, reading_quantum)
from dipnet.preprocessing.dip_agreement import dip_agreement
from dipnet.preprocessing.level_trend import level_fall
from dipnet.preprocessing.symmetry_moments import MISFIT_LIMIT, P_LIMIT, SymmetryFit, group_closure, symmetry_fit
from dipnet.preprocessing.validation import NOISE_LEAK_MAX, beyond_ball_message, object_reach
from dipnet.solvers.base import measured_profiles, measured_sigma
from dipnet.solvers.optimize import EmptySupportError, support_hull
from dipnet.solvers.priors import symmetry_maps

log = logging.getLogger(__name__)

#: Residual allowed above the noise's own share when the noise is estimated from the profiles (which holds signal)
RESIDUAL_FACTOR = 3.0
#: The same when the measurement states its noise (``sigma``): a correct result's residual is its noise and its grid
#: error in quadrature, and a stated sigma overstates the profiles' own noise (empty slabs keep it whole);
#: see :func:`allowed_residual` and docs/benchmarks/consistency.md
STATED_RESIDUAL_FACTOR = 1.25
RESIDUAL_FLOOR = 0.05  # relative residual below which no result is flagged at any grid (voxel discretisation)
#: A grid of ``n`` voxels per axis leaves a binary shape up to about ``RESIDUAL_FLOOR_VOXELS / n`` of relative
#: residual (its surface voxels), measured on the correct results of docs/benchmarks/consistency.md
RESIDUAL_FLOOR_VOXELS = 3.0
VOLUME_TOL = 0.05  # |volume ratio - 1| allowed at the least
LEVEL_DROP_TOL = 0.01  # a dip's level falling by more than this share of the volume (and its noise): a cavity flooding
EXCESS_TOTAL_TOL = 0.005  # a dip measuring more than the median dip by this share of the volume (and its noise)
EXCESS_SIGMAS = 5.0  # ... and by this many of its noise sigmas: trapped air
HULL_FILL_MIN = 0.04  # measured volume / the dips' support hull below which the volume's unit is suspect
HULL_FILL_MAX = 1.1  # above it the dips measure more than the region they bound can hold (a box fills ~1)
FLOOR_SIGMAS = 3.0  # a profile floor within this many noise sigmas of 0 is noise
FLOOR_SPREAD = 0.25  # the dips' floors agree (a drift's floor) when their robust spread is at most this share
# a drift of the floor that puts less than this share of the volume beyond the slabs: untested
FLOOR_BEYOND_MATERIAL = 0.01
FLOOR_BEYOND_MIN = 0.25  # readings beyond the slabs holding less than this share of a drift's: the floor is no drift
#: The share of what the threshold adds or removes that lies more than one voxel deep inside the regions it changes,
#: above which the occupancy is a smeared field, not a shape's partial voxels (:func:`threshold_change_depth`; true
#: partial volumes: at most 0.0043, nine times below it; min-norm from 12 dips: 0.14-0.42; empty solves: 0.66-0.68)
SMEAR_DEPTH_MAX = 0.04
#: Changes of the threshold below this share of a voxel (a solver's tails) are left out of that share
SMEAR_CHANGE_MIN = 0.05
#: A binary shape holding more than this many times its occupancy's volume: no threshold of 0.5 makes that of a
#: shape's partial voxels (each at most doubles)
THRESHOLD_GAIN_MAX = 2.0
#: A stated noise above this many times the readings' own is named (correct simulations: 0.86-1.30 at 1 mm steps,
#: see the module docstring), and one below its inverse when the readings' estimate holds their noise alone
NOISE_RATIO_MAX = 3.0
#: A result whose binary shape's residual is below this share of what a stated noise explains fits its dips far
#: closer than that noise allows: the noise is overstated (a shape that fits the dips and not their noise leaves about
#: all of it; ``voxel`` results and the truth's own voxels on 183 simulated scans with a stated 5-40 dB noise left at
#: least 0.46 and 0.55 of it, ``scripts/bench_consistency.py``), which the readings' own scatter shows only where
#: there are readings (:data:`NOISE_RATIO_MAX`). What the noise explains counts up to 1, what the empty shape leaves:
#: a noise said to explain more than the profiles themselves (the monotone slabs of readings at -20 dB hold far less
#: noise than the readings: 2D, 10 dips, a ``voxel`` result under that true noise left 0.18 of the stated 3.7) is
#: not read from it
RESIDUAL_NOISE_SHARE_MIN = 0.2
#: The disagreeing dips a message names (the rest are counted)
MAX_NAMED_DIPS = 8


class DataConsistencyWarning(UserWarning):
    """A reconstruction does not explain its measurement within what the noise explains."""


@dataclass
class Consistency:
    """How well a reconstruction explains a measurement (see the module docstring).

    Volumes in mm^3 (mm^2 in 2D: ``volume_unit`` names it); residuals relative to ``||g||``; ``noise_source`` is
    ``"sigma"`` (the measurement's own) or ``"estimated"`` (from the profiles).
    """

    profile_residual: float
    profile_residual_continuous: float
    profile_residual_expected: float
    residual_limit: float
    noise_source: str
    measured_volume_mm3: float
    reconstructed_volume_mm3: float
    continuous_volume_mm3: float
    volume_ratio: float
    volume_ratio_noise: float
    volume_limit: float
    grid_volume_fraction: float
    hull_fill: float = float("nan")
    hull_fill_min: float = HULL_FILL_MIN
    height_trend_pivot_mm: float = float("nan")
    height_trend_offset_mm: float = float("nan")
    height_trend_limit_mm: float = float("nan")
    profile_floor_mm3: float = float("nan")
    profile_floor_share: float = float("nan")
    profile_floor_limit_mm3: float = float("nan")
    outside_share: float = float("nan")
    outside_limit: float = float("nan")
    object_reach_mm: float = float("nan")
    working_radius_mm: float = float("nan")
    floor_beyond_ratio: float = float("nan")
    quantum_volume_mm3: float = float("nan")
    mean_slab_mm3: float = float("nan")
    level_fall_share: float = float("nan")
    level_fall_sigmas: float = float("nan")
    level_drop_share: float = float("nan")
    level_drop_dips: int = 0
    excess_total_share: float = float("nan")
    excess_total_dips: int = 0
    reading_noise_mm3: float = float("nan")
    reading_noise_ratio: float = float("nan")
    reading_noise_leak: float = float("nan")
    dip_outliers: list[int] = field(default_factory=list)
    dip_outlier_share: float = float("nan")
    dip_outlier_sigmas: float = float("nan")
    dip_outlier_order: int = 0
    dip_agreement_tested: int = 0
    threshold_change_depth: float = float("nan")
    symmetry_misfit: float = float("nan")
    symmetry_misfit_p: float = float("nan")
    symmetry_misfit_order: int = 0
    symmetry_misfit_limit: float = MISFIT_LIMIT
    symmetry_declared: str = ""
    symmetry_rejected: bool = False
    volume_unit: str = "mm^3"
    verdict: str = "consistent"
    warnings: list[str] = field(default_factory=list)
    plan_warning: str = ""
    underdetermined: str = ""

    def metrics(self) -> dict:
        """The numbers as a flat, JSON-serialisable dict (for ``metrics.json``)."""
        out = asdict(self)
        out["consistency_warnings"] = out.pop("warnings")
        out["consistency"] = out.pop("verdict")
        return out


def height_trend(measurement: DipMeasurement) -> tuple[float, float, float]:
    """``(-a, -b, limit)`` mm: the dips' centroids fitted as ``c . theta + a (cos r - 1) + b sin r``
    (``r`` the tilt from the z axis): the pivot and tilt-axis offset the rig geometry misses
    (:meth:`~dipnet.core.geometry.RigGeometry.height_shift`), and the size a trend must exceed to
    be reported: half a slab or 3 standard errors, whichever is larger. NaNs in 2D, with fewer
    than 8 dips, when the directions cannot separate the trend from the centroid (one tilt, one
    spin), or when some profiles are not measured whole dips (truncated dips kept, symmetry
    images, interpolated directions: their centroids are not the object's).
    """
    meta = measurement.metadata or {}
    if (meta.get("recorded") or {}).get("truncated") or "symmetry_group_order" in meta \
            or meta.get("interpolated_orientations"):
        return float("nan"), float("nan"), float("nan")
    d = measurement.directions.double().numpy()
    p = measurement.profiles.double().numpy()
    totals = p.sum(1)
    if d.shape[1] != 3 or len(d) < 8 or not (totals > 0).all():
        return float("nan"), float("nan"), float("nan")
    h = measurement.slab_thickness
    centroid = (p * measurement.slab_centres().numpy()).sum(1) / totals
    r = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    design = np.column_stack([d, np.cos(r) - 1.0, np.sin(r)])
    if np.linalg.matrix_rank(design, tol=1e-6) < design.shape[1]:
        return float("nan"), float("nan"), float("nan")
    coef, *_ = np.linalg.lstsq(design, centroid, rcond=None)
    residual = centroid - design @ coef
    s2 = float(residual @ residual) / max(1, len(d) - design.shape[1])
    se = np.sqrt(s2 * np.diag(np.linalg.inv(design.T @ design)))
    return float(-coef[3]), float(-coef[4]), float(max(0.5 * h, 3 * se[3], 3 * se[4]))


def excess_totals(measurement: DipMeasurement) -> tuple[float, int]:
    """``(share, dips)``: how far the largest profile total exceeds the median one, over the median, and how many
    dips exceed it by more than :data:`EXCESS_SIGMAS` of their noise and :data:`EXCESS_TOTAL_TOL` of the volume.

    Every dip measures the same object, so the totals agree within noise: a preprocessed total errs as one slab
    does (the difference of the cumulative volume's errors at its two ends: the measurement's median ``sigma``
    per dip, else :func:`~dipnet.core.measurement.estimate_slab_sigma`), and never less than the totals' own
    robust spread (1.4826 MAD), which holds independent slab errors and a real rig's systematic ones (the
    authors' cats: totals from -7.9 % to +2.4 % of the median, a spread of 1.3 %). A dip that measures *more*
    than the rest holds something the object does not: air trapped in a cavity that opens downward along it
    (:mod:`dipnet.simulator.pockets`). Dips that measure less are left to the other checks (a dip cut short, an
    object beyond the slabs). On 20 random scans of the 3D built-ins and bundled meshes without pockets (20-40 dB
    and noise-free), the largest excess was 0.5 % of the volume at 2.1 slab sigmas."""
    totals = measurement.profiles.double().sum(1).numpy()
    median = float(np.median(totals))
    if not median > 0:
        return float("nan"), 0
    if measurement.sigma is not None:
        sigma = np.median(measurement.sigma.double().numpy(), axis=1)
    else:
        sigma = np.full(totals.shape, estimate_slab_sigma(measurement.profiles))
    excess = totals - median
    sigma = np.maximum(sigma, 1.4826 * float(np.median(np.abs(excess))))
    over = (excess > EXCESS_SIGMAS * sigma) & (excess > EXCESS_TOTAL_TOL * median)
    return float(excess.max() / median), int(over.sum())


def profile_floor(measurement: DipMeasurement, measured_volume: float) -> tuple[float, float]:
    """``(floor, share)``: the median over the dips of each profile's second-smallest slab volume
    (mm^3; mm^2 in 2D) and ``floor * M / measured_volume`` for ``M`` slabs per dip: the share of the
    measured volume a constant floor under every slab would add. The first and last slab are left
    out and the second-smallest taken, as a dip's first and last slabs in the water may be partial.
    On the 16 bundled meshes scaled to fill the working ball (24 slabs, 30 dips, 30 dB) the share is
    at most 0.8 %; a drift of 0.0005 mm/s gives 4-61 %. NaNs with fewer than 6 slabs per dip.
    """
    floors = dip_floors(measurement)
    if floors is None:
        return float("nan"), float("nan")
    floor = float(np.median(floors))
    return floor, floor * measurement.n_slabs / measured_volume


def dip_floors(measurement: DipMeasurement) -> np.ndarray | None:
    """Each dip's second-smallest slab volume but its first and last ``(K,)`` (mm^3; mm^2 in 2D), or ``None``
    with fewer than 6 slabs per dip (see :func:`profile_floor`)."""
    p = measurement.profiles.double().numpy()
    return None if p.shape[1] < 6 else np.sort(p[:, 1:-1], axis=1)[:, 1]


def floor_limit(measurement: DipMeasurement, slab_sigma: float) -> float:
    """The profile floor (:func:`profile_floor`) above which it is no noise (mm^3; mm^2 in 2D): ``FLOOR_SIGMAS``
    slab sigmas ``slab_sigma``, or, when the dips' own floors agree (their robust spread at most
    ``FLOOR_SPREAD`` of their median, as a drift's do and an object's thinnest slabs along other directions
    do not), ``FLOOR_SIGMAS`` standard errors of the median of the ``K`` dips' floors (``sqrt(pi / 2)`` slab
    sigmas over ``sqrt(K)``). A slab sigma estimated on a coarse grid also takes the object's own
    curvature: with it alone, a drift that carried 10 % of the volume at 16^3-24^3 stayed under the limit and
    the run passed as consistent. NaN with fewer than 6 slabs per dip."""
    floors = dip_floors(measurement)
    if floors is None:
        return float("nan")
    median = float(np.median(floors))
    spread = 1.4826 * float(np.median(np.abs(floors - median)))
    if spread <= FLOOR_SPREAD * abs(median):
        return FLOOR_SIGMAS * math.sqrt(math.pi / 2) * slab_sigma / math.sqrt(len(floors))
    return FLOOR_SIGMAS * slab_sigma


def beyond_slabs(measurement: DipMeasurement, floor_mm3: float) -> float:
    """The largest share of a dip's volume beyond its slabs (the measurement's ``outside_share`` metadata,
    from preprocessing), or 0 when a level drift explains it: a drift that puts ``floor_mm3`` (mm^3; mm^2
    in 2D) under every slab puts ``floor_mm3 / h`` per mm of readings outside the slabs (``outside_mm``)
    too; the dips' volume there within a factor 2 of that is taken for the drift. NaN without the metadata.
    """
    meta = measurement.metadata or {}
    shares = np.asarray(meta.get("outside_share", []), dtype=np.float64)
    if shares.size == 0:
        return float("nan")
    spans = np.asarray(meta.get("outside_mm", []), dtype=np.float64)
    if floor_mm3 > 0 and spans.size == shares.size:
        totals = float(measurement.profiles.double().sum(1).mean())
        beyond = float(np.mean(shares / np.clip(1.0 - shares, 1e-12, None))) * totals
        drift = floor_mm3 / measurement.slab_thickness * float(spans.mean())
        if 0.5 * drift <= beyond <= 2.0 * drift:
            return 0.0
    return float(shares.max())


def floor_beyond_ratio(measurement: DipMeasurement, floor_mm3: float) -> float:
    """What the dips' readings beyond their slabs hold over what a level drift that puts ``floor_mm3`` (mm^3;
    mm^2 in 2D) under every slab would put there (``floor_mm3 / h`` per mm of readings beyond the slabs,
    ``outside_mm``): about 1 for a drift; far below 1 when the floor is the object's own, its slabs so coarse
    that it fills every inner one (2D, 24 pixels, 7 slabs: 0.02). NaN without the metadata, without readings
    beyond the slabs, or when a drift of that floor would put there less than 1 % of the volume."""
    meta = measurement.metadata or {}
    shares = np.asarray(meta.get("outside_share", []), dtype=np.float64)
    spans = np.asarray(meta.get("outside_mm", []), dtype=np.float64)
    if not floor_mm3 > 0 or shares.size == 0 or spans.size != shares.size:
        return float("nan")
    totals = float(measurement.profiles.double().sum(1).mean())
    drift = floor_mm3 / measurement.slab_thickness * float(spans.mean())
    if not drift > FLOOR_BEYOND_MATERIAL * totals:
        return float("nan")
    return float(np.mean(shares / np.clip(1.0 - shares, 1e-12, None))) * totals / drift


def estimated_slab_noise(target: torch.Tensor, metadata: dict) -> tuple[float, str]:
    """``(sigma, source)``: the per-slab noise (mm^3) of profiles ``target`` ``(K, M)`` whose noise is not stated.

    :func:`~dipnet.core.measurement.estimate_slab_sigma` of the profiles holds their signal's curvature too, and on
    coarse slabs mostly that (a noise-free chamber box at 24^3, 4.5 mm slabs: 0.042 of the profiles' norm, where the
    readings scatter by 0.0004), which lets a shape that misses its data pass. A slab is the difference of two
    cumulative readings, so ``sqrt(2)`` times the noise of one reading (preprocessing's ``reading_noise_volume``
    metadata, itself an upper bound: the rise's curvature leaks into it) bounds its noise from above too: the smaller
    of the two is used (``source`` ``"readings"``), the profiles' own estimate without readings (``"estimated"``).
    """
    sigma, reading = estimate_slab_sigma(target), reading_slab_sigma(metadata)
    if reading is not None and reading < sigma:
        return reading, "readings"
    return sigma, "estimated"


def allowed_residual(expected: float, n: int, stated: bool, factor: float | None = None,
                   floor: float = RESIDUAL_FLOOR) -> float:
    """The relative profile residual above which a binary result is flagged: ``hypot(f expected, floor_n)``, the
    noise's share ``expected`` (times ``f``: ``factor``, else :data:`STATED_RESIDUAL_FACTOR` for a stated noise,
    :data:`RESIDUAL_FACTOR` for one estimated from the profiles) and the grid's own error in quadrature, the latter
    ``floor_n = max(floor, RESIDUAL_FLOOR_VOXELS / n)`` for ``n`` voxels per axis. On 230 random cases
    (docs/benchmarks/consistency.md, whose rows chose its two constants) it flagged 1.8 % of the correct
    results at 24^3 and none at 32^3, where ``max(3 expected, 0.05)`` flagged 9.8 % and 5.8 %, and detected 95 % and
    93 % of wrong shapes instead of 87 % and 81 % (at 5-15 dB: 85 % and 66 % instead of 40 % and 20 %)."""
    f = factor if factor is not None else STATED_RESIDUAL_FACTOR if stated else RESIDUAL_FACTOR
    return math.hypot(f * expected, max(floor, RESIDUAL_FLOOR_VOXELS / n))


def threshold_change_depth(occupancy: np.ndarray, binary: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The share of what thresholding ``occupancy`` into ``binary`` adds or removes that lies more than one voxel
    deep inside the regions it changes (0 to 1; NaN when it changes nothing).

    The change of a voxel is ``|binary - occupancy|`` (the occupancy clipped to ``[0, 1]``: a share of the voxel;
    changes below :data:`SMEAR_CHANGE_MIN` left out, and voxels outside ``mask``, the operator's working region);
    its part more than one voxel deep is what a grey erosion over the face neighbours leaves of it. A shape's
    partial-volume occupancy changes only where its surface or a part thinner than a voxel crosses the voxels, a
    layer one or two voxels thick, which the erosion removes (a plate of 0.4 voxel: 0; the true occupancies of the
    built-in chamber box and ten bundled meshes at 16^3 and 24^3: at most 0.004); a field smeared over thick regions
    keeps much of it (min-norm from 12 dips at 16^3-24^3: 0.14-0.42; an empty solve: 0.66-0.68).
    """
    change = np.abs(binary.astype(np.float64) - np.clip(occupancy.astype(np.float64), 0.0, 1.0))
    if mask is not None:
        change = np.where(mask, change, 0.0)
    change = np.where(change >= SMEAR_CHANGE_MIN, change, 0.0)
    total = float(change.sum())
    cross = scipy.ndimage.generate_binary_structure(change.ndim, 1)  # a voxel and its face neighbours
    deep = scipy.ndimage.grey_erosion(change, footprint=cross, mode="constant", cval=0.0)  # beyond the grid: 0
    return float(deep.sum()) / total if total > 0 else float("nan")


def _relative_residual(operator: DipOperator, volume: torch.Tensor, target: torch.Tensor) -> float:
    with torch.no_grad():
        predicted = operator(volume.to(torch.float64))
    return float((predicted - target).norm() / target.norm().clamp(min=1e-300))


def check_consistency(measurement: DipMeasurement, operator: DipOperator, reconstruction: Reconstruction, *,
                      residual_factor: float | None = None, residual_floor: float = RESIDUAL_FLOOR,
                      volume_tol: float = VOLUME_TOL, hull_fill_min: float = HULL_FILL_MIN,
                      warn: bool = True) -> Consistency:
    """Residual, volume ratio and verdict of ``reconstruction`` against ``measurement``.

    Args:
        measurement: the data (any slabs; resampled onto the operator's).
        operator: the dip operator of the reconstruction's grid and the measurement's directions.
        reconstruction: the result (its ``binary`` and ``occupancy`` are both checked).
        residual_factor: flag a residual above this multiple of what the noise explains (in quadrature with the
            grid's floor; ``None``: :data:`STATED_RESIDUAL_FACTOR` for a stated noise, :data:`RESIDUAL_FACTOR` for
            an estimated one; :func:`allowed_residual`).
        residual_floor: never flag a relative residual below this (voxel discretisation; raised on coarse grids).
        volume_tol: flag ``|volume_ratio - 1|`` above this (or 3 noise spreads, if larger).
        hull_fill_min: flag a measured volume filling less than this share of the dips' support hull.
        warn: log and ``warnings.warn`` a :class:`DataConsistencyWarning` per failed check, and a ``UserWarning``
            naming why the dips are too few to determine a shape (the verdict ``underdetermined``), else (not part
            of the verdict) the band of directions no dip reaches when it is wider than
            :data:`~dipnet.evaluation.resolvability.UNMEASURED_BAND_DEG` (the sides are then the priors' guess).
    """
    got = (measurement, operator, reconstruction)
    if not all(isinstance(a, cls) for a, cls in zip(got, (DipMeasurement, DipOperator, Reconstruction))):
        raise TypeError(f"check_consistency(measurement, operator, reconstruction) takes a DipMeasurement, "
                        f"a DipOperator and a Reconstruction (a solver's result), "
                        f"got {', '.join(type(a).__name__ for a in got)}")
    if not reconstruction.grid.matches(operator.grid):  # not !=: extents equal to 1e-9 are the same voxels
        raise ValueError(f"the reconstruction's grid {reconstruction.grid} is not the operator's {operator.grid}: "
                         "check it with the operator its solver used")
    target = measured_profiles(measurement, operator)
    binary = torch.from_numpy(reconstruction.binary)
    occupancy = reconstruction.occupancy.detach().cpu()
    voxel = operator.grid.voxel_volume
    mask = operator.mask
    measured, spread = robust_volume(measurement.profiles)
    if not measured > 0:
        raise ValueError(f"the measurement's profiles hold no volume ({measured:g} {operator.grid.volume_unit}): "
                         "nothing to check against")
    on_grid, _ = robust_volume(target)
    quantum = reading_quantum(measurement)
    rounding = quantum.slab_sigma if quantum is not None else 0.0  # a sigma of preprocess holds it already
    sigma = measured_sigma(measurement, operator)  # on the operator's slabs, as the target
    if sigma is not None:
        noise_norm, source = float(sigma.double().pow(2).sum().sqrt()), "sigma"
    else:
        slab_noise, source = estimated_slab_noise(target, measurement.metadata or {})
        noise_norm = math.hypot(slab_noise, rounding) * math.sqrt(target.numel())
    expected = noise_norm / float(target.norm().clamp(min=1e-300))
    recon_volume = float((binary & mask).sum()) * voxel
    result = Consistency(
        profile_residual=_relative_residual(operator, binary, target),
        profile_residual_continuous=_relative_residual(operator, occupancy, target),
        profile_residual_expected=expected,
        residual_limit=allowed_residual(expected, operator.grid.n, sigma is not None, residual_factor, residual_floor),
        noise_source=source, measured_volume_mm3=measured, reconstructed_volume_mm3=recon_volume,
        continuous_volume_mm3=float((occupancy.double() * mask).sum()) * voxel,
        volume_ratio=recon_volume / measured, volume_ratio_noise=math.hypot(spread, rounding) / measured,
        volume_limit=max(volume_tol, 3 * math.hypot(spread, rounding) / measured),
        grid_volume_fraction=on_grid / measured,
        hull_fill=_hull_fill(measured, target, operator), hull_fill_min=hull_fill_min,
        volume_unit=operator.grid.volume_unit)
    result.threshold_change_depth = threshold_change_depth(occupancy.numpy(), reconstruction.binary,
                                                           mask.cpu().numpy())
    (result.height_trend_pivot_mm, result.height_trend_offset_mm,
     result.height_trend_limit_mm) = height_trend(measurement)
    if quantum is not None:
        spanned = object_slabs(measurement.profiles)
        result.quantum_volume_mm3, result.mean_slab_mm3 = quantum.volume, measured / spanned
        result.height_trend_limit_mm = max(result.height_trend_limit_mm, centroid_allowance(
            quantum, measured, measurement.slab_thickness, spanned))  # NaN stays NaN
    result.profile_floor_mm3, result.profile_floor_share = profile_floor(measurement, measured)
    slab_sigma = _slab_sigma(measurement)
    result.profile_floor_limit_mm3 = floor_limit(measurement, slab_sigma)
    result.outside_share = beyond_slabs(measurement, result.profile_floor_mm3)
    result.floor_beyond_ratio = floor_beyond_ratio(measurement, result.profile_floor_mm3)
    result.outside_limit = max(BEYOND_SLABS_TOL, FLOOR_SIGMAS * slab_sigma / measured)
    if result.outside_share > result.outside_limit:  # NaN compares False; a share within the noise is noise
        result.grid_volume_fraction *= 1.0 - result.outside_share
    result.object_reach_mm, _ = object_reach(measurement)
    result.working_radius_mm = operator.grid.radius
    metadata = measurement.metadata or {}
    result.reading_noise_mm3, result.reading_noise_ratio, result.reading_noise_leak = (
        _metadata_number(metadata, key) for key in ("reading_noise_volume", "reading_noise_ratio",
                                                    "reading_noise_leak"))
    if "tail_slope" in metadata and "readings_per_dip" in metadata:
        result.level_fall_share, result.level_fall_sigmas = level_fall(
            metadata["tail_slope"], metadata["readings_per_dip"], measured)
    result.excess_total_share, result.excess_total_dips = excess_totals(measurement)
    if "level_drop" in metadata:
        drops = [float(row[0]) for row in metadata["level_drop"]]
        result.level_drop_share = max(drops, default=0.0) / measured
        result.level_drop_dips = sum(d > 0 for d in drops)
    agreement = dip_agreement(measurement)
    result.dip_outliers, result.dip_outlier_share = agreement.outliers, agreement.share
    result.dip_outlier_sigmas, result.dip_outlier_order = agreement.sigmas, agreement.order
    result.dip_agreement_tested = agreement.tested
    fit, result.symmetry_declared = declared_symmetry_fit(measurement, reconstruction)
    result.symmetry_misfit, result.symmetry_misfit_p = fit.misfit, fit.p_value
    result.symmetry_misfit_order, result.symmetry_rejected = fit.order, fit.rejected
    from dipnet.evaluation.resolvability import underdetermined_plan, warn_unmeasured_band  # (it imports this one)
    result.underdetermined = underdetermined_plan(measurement.directions) or ""
    result.warnings = _findings(result, metadata.get("symmetry_group_order", 1), quantum, operator.grid) + \
        _refit_findings(result, reconstruction.info.get("surface_refit") or {})
    result.verdict = "inconsistent" if result.warnings else "underdetermined" if result.underdetermined else \
        "consistent"
    if warn:
        for message in result.warnings:
            log_and_warn(log, message, DataConsistencyWarning, stacklevel=2)
        if result.underdetermined:
            log_and_warn(log, result.underdetermined, stacklevel=2)
            result.plan_warning = result.underdetermined
        else:  # the plan's gaps: the verdict stands
            result.plan_warning = warn_unmeasured_band(measurement.directions) or ""
    return result


def declared_symmetry_fit(measurement: DipMeasurement, reconstruction: Reconstruction) -> tuple[SymmetryFit, str]:
    """How well the symmetries the result assumed fit the measured dips' moments
    (:mod:`dipnet.preprocessing.symmetry_moments`), and which they were: the group whose images the measurement
    holds (``metadata["symmetry_fit"]``, tested on the dips before the images were added: ``"images"``) and every
    symmetry the solver declared (``reconstruction.info["symmetries"]``, about the grid's centre: ``"prior"``),
    the worst of them (a rejected one first, then the largest misfit). A solver's symmetry is not tested on a
    measurement that holds images (they fit the images' group by construction). ``(SymmetryFit(), "")`` when
    nothing was declared."""
    meta = measurement.metadata or {}
    fits = []
    if isinstance(meta.get("symmetry_fit"), dict):
        fits.append((SymmetryFit.from_metadata(meta["symmetry_fit"]), "images"))
    if "symmetry_group_order" not in meta:
        for spec in (reconstruction.info or {}).get("symmetries", []):
            maps = [m.numpy() for m in symmetry_maps(measurement.ndim, **spec)]
            fits.append((symmetry_fit(measurement, group_closure(maps)), "prior"))
    if not fits:
        return SymmetryFit(), ""
    return max(fits, key=lambda f: (f[0].rejected, np.nan_to_num(f[0].misfit, nan=-1.0)))


def _metadata_number(metadata: dict, key: str) -> float:
    """``metadata[key]`` as a float; NaN when it is missing or ``None``."""
    value = metadata.get(key)
    return float("nan") if value is None else float(value)


def _slab_sigma(measurement: DipMeasurement) -> float:
    """The measurement's typical per-slab noise sigma (mm^3): the median of its own ``sigma``, else
    estimated from its profiles."""
    if measurement.sigma is not None:
        return float(measurement.sigma.double().median())
    return estimate_slab_sigma(measurement.profiles)


def _hull_fill(measured: float, target: torch.Tensor, operator: DipOperator) -> float:
    """``measured`` (mm^3) over the volume of the data's support hull; NaN when no voxel is left."""
    try:
        hull = support_hull(target, operator.grid, operator.directions, operator.slab_edges(), margin=0.0)
    except EmptySupportError:
        return float("nan")
    return measured / (float(hull.sum()) * operator.grid.voxel_volume)


def _findings(c: Consistency, symmetry_order: int = 1, quantum: Quantum | None = None,
              grid: Grid | None = None) -> list[str]:
    """One plain message per failed check; ``symmetry_order``: the order of a declared symmetry group whose
    images of the dips the data hold (:func:`~dipnet.preprocessing.symmetry.expand_symmetry`), named as a cause;
    ``quantum``: the sensor's reading quantum, named as the cause when it is coarse against a slab (and then the
    rig-geometry and unit hints, which its rounding alone sets off, are left out); ``grid``: the reconstruction's,
    whose working ball an object reaching beyond is named."""
    out = []
    # self-calibration fits a drift from 3D dips only (their tilts and spins): 2D's slabs are areas, mm^2
    fit_drift = ("calibration=self fits the drift" if c.volume_unit != "mm^2" else
                 "2D dips have no self-calibration (calibration=self is 3D): measure the drift and take it out")
    coarse = quantum is not None and c.quantum_volume_mm3 >= COARSE_SHARE * c.mean_slab_mm3
    if coarse:
        out.append(coarse_quantum_message(quantum, c.mean_slab_mm3, c.volume_unit))
    suspects = "the rig model (start heights, geometry, cross-section) or the priors disagree with the data"
    flooding = c.level_drop_share > LEVEL_DROP_TOL  # NaN compares False
    if flooding or c.excess_total_dips:
        suspects = f"cavities that keep air or stay dry (below) make the dips disagree, or {suspects}"
    if c.excess_total_dips:
        out.append(f"{c.excess_total_dips} dip(s) measure more than the median dip, "
                   f"by up to {c.excess_total_share:.1%} "
                   "of the volume and more than their noise: air trapped in a cavity of the object that opens "
                   "downward along those dips displaces water as the object does (or the level rose during them). "
                   "Vent the cavity (a second opening lets the air out), or fill or seal it and measure the object "
                   "without it")
    if flooding:
        out.append(f"{c.level_drop_dips} dip(s) show the water level falling while the object went down, by up to "
                   f"{c.level_drop_share:.1%} of the measured volume: water pouring into a cavity of the object that "
                   "stayed dry until the water reached its rim (a vessel). The dip transform assumes water reaches "
                   "every cavity as soon as the water line passes it; a vessel's dips, and the dips of a cavity that "
                   "opens downward and traps its air, measure more than the object. Vent the cavity (a second "
                   "opening lets the air out), or fill or seal it and measure the object without it")
    if symmetry_order > 1:
        suspects = (f"the declared symmetry (order {symmetry_order}: every dip copied to its images) may not be the "
                    f"object's (run without symmetry to check), or {suspects}")
    beyond = c.outside_share > c.outside_limit  # NaN compares False
    over_ball = c.object_reach_mm >= c.working_radius_mm * (1 - 1e-9)  # NaN compares False
    if over_ball and grid is not None:
        out.append(beyond_ball_message(c.object_reach_mm, grid))
    if c.grid_volume_fraction < 1 - c.volume_limit or beyond:
        readings = (f" (a dip's readings hold up to {c.outside_share:.1%} of its volume beyond the slabs, which its "
                    "profile leaves out, and fill its slabs to their ends)") if beyond else ""
        out.append(f"the grid's slabs hold only {c.grid_volume_fraction:.1%} of the measured volume{readings}: the "
                   "object reaches beyond the working range: raise extent_mm (or check the start heights)")
    if c.profile_residual_continuous > c.residual_limit:
        out.append(f"the occupancy misses its data: relative profile residual {c.profile_residual_continuous:.3f}, "
                   f"noise explains {c.profile_residual_expected:.3f} ({c.noise_source}): {suspects}")
    if c.profile_residual > c.residual_limit:
        out.append(f"the binary shape misses its data: relative profile residual {c.profile_residual:.3f} "
                   f"(occupancy: {c.profile_residual_continuous:.3f}), noise explains "
                   f"{c.profile_residual_expected:.3f} ({c.noise_source}){_binary_hint(c)}")
    trend = max(abs(c.height_trend_pivot_mm), abs(c.height_trend_offset_mm))
    if trend > c.height_trend_limit_mm and not coarse:  # NaN compares False
        out.append(f"the dips' heights trend with their tilt as a wrong rig geometry leaves them: the pivot looks "
                   f"off by {c.height_trend_pivot_mm:+.2f} mm and the tilt-axis offset by "
                   f"{c.height_trend_offset_mm:+.2f}"
                   f" mm (more than {c.height_trend_limit_mm:.2f} mm): calibrate the rig (calibration=self, "
                   "scripts/calibrate.py)")
    drift_free = c.floor_beyond_ratio < FLOOR_BEYOND_MIN  # NaN compares False: no readings to tell by
    if abs(c.profile_floor_mm3) > c.profile_floor_limit_mm3 and abs(c.profile_floor_share) > c.volume_limit \
            and not beyond and not over_ball and not drift_free:  # an object beyond fills the slabs to their ends
        out.append(f"every dip holds {c.profile_floor_mm3:+.4g} {c.volume_unit} per slab where its slabs should be "
                   "empty (before "
                   f"the object touches the water and after it is under): {c.profile_floor_share:+.1%} of the "
                   "measured volume, which the reconstruction takes for object. A level that drifts in time (the "
                   f"sensor's drift, a leak or an inflow) does this: calibrate it ({fit_drift}), or check the tank; "
                   "or the object fills the working range to its ends (raise extent_mm)")
    if c.level_fall_share > c.volume_limit and c.level_fall_sigmas > FLOOR_SIGMAS:  # NaN compares False
        out.append(f"the water level falls after the object is under, where it must stay put: over a dip the fall "
                   f"takes {c.level_fall_share:.1%} of the measured volume "
                   f"({c.level_fall_sigmas:.0f} standard errors), "
                   "and the monotone slabs hide it, so every profile, the measured volume and the shape are too small "
                   "by about that much. A leak, evaporation or a level sensor drifting down does this: check the tank "
                   f"and the sensor, or fit the drift ({fit_drift})")
    if c.reading_noise_ratio < 1 / NOISE_RATIO_MAX and c.reading_noise_leak < NOISE_LEAK_MAX:  # NaN compares False
        out.append(f"the stated noise is only {c.reading_noise_ratio:.2f} of what the readings scatter by "
                   f"(one reading: {c.reading_noise_mm3:.3g} {c.volume_unit}): the solvers' prior weights, "
                   "set from it, are too small "
                   "and the shape takes noise for object, and the residual limit it sets is too strict. Correct the "
                   "sensor's noise_sigma or snr_db (or leave the noise unstated to have it estimated)")
    if c.dip_outliers:
        named = ", ".join(str(i) for i in c.dip_outliers[:MAX_NAMED_DIPS]) + (
            f" and {len(c.dip_outliers) - MAX_NAMED_DIPS} more" if len(c.dip_outliers) > MAX_NAMED_DIPS else "")
        out.append(f"{len(c.dip_outliers)} dip(s) disagree with the others (dips {named}, counted from 0): their "
                   f"order-{c.dip_outlier_order} moments miss what the other dips give one object by up to "
                   f"{c.dip_outlier_share:.1%} of its size ({c.dip_outlier_sigmas:.0f} noise sigmas). A direction "
                   "filed under the wrong dip (rows swapped, an orientation log one dip off) or an object that moved "
                   "in its holder during the scan does this, and the solvers fit such dips anyway: check the "
                   "recording's orientations and the holder, and rescan those dips or remove them from the recording")
    if c.symmetry_rejected:
        if c.symmetry_declared == "images":
            what, remedy = "every dip copied to its images", "declare the object's own symmetry about z, or none"
        else:
            what, remedy = "the solver's symmetry prior", ("drop it (solver.priors.symmetry.weight=0; solver=implicit: "
                                                           "solver.symmetry=null) or declare the object's own")
        out.append(f"the declared symmetry ({what}) does not fit the dips: their order-{c.symmetry_misfit_order} "
                   f"moments miss the symmetric fit by {c.symmetry_misfit:.1%} of the object's own (p = "
                   f"{c.symmetry_misfit_p:.1g}; a symmetric object: below {c.symmetry_misfit_limit:.0%} or p above "
                   f"{P_LIMIT:g}), so the shape holds mirrored or rotated copies of parts the object does not have: "
                   f"{remedy}")
    if c.reading_noise_ratio > NOISE_RATIO_MAX:  # NaN compares False
        out.append(f"the stated noise is {c.reading_noise_ratio:.1f} times what the readings scatter by (one reading: "
                   f"{c.reading_noise_mm3:.3g} {c.volume_unit}): the solvers' prior weights, set from it, over-smooth "
                   f"the shape, and the residual limit ({c.residual_limit:.3f}) it sets is too generous to show it. "
                   "Correct the sensor's noise_sigma or snr_db (or leave the noise unstated to have it estimated)")
    elif c.noise_source == "sigma" and not c.underdetermined \
            and c.profile_residual < RESIDUAL_NOISE_SHARE_MIN * min(c.profile_residual_expected, 1.0):
        # dips too few to determine a shape (underdetermined) leave room to fit their noise; what the noise explains
        # counts up to 1, what the empty shape leaves
        out.append(f"the result fits its dips far closer than their stated noise allows: relative profile residual "
                   f"{c.profile_residual:.3g}, {c.profile_residual / c.profile_residual_expected:.2f} of the "
                   f"{c.profile_residual_expected:.3g} the stated noise explains (a shape that fits the dips and not "
                   f"their noise leaves about all of it; under {RESIDUAL_NOISE_SHARE_MIN:g} the noise is overstated): "
                   "the solvers' prior weights, set from it, over-smooth the shape, and the residual limit "
                   f"({c.residual_limit:.3g}) it sets is too generous to show a wrong one. Check the measurement's "
                   f"sigma (its unit: {c.volume_unit} per slab; a variance for a standard deviation) or the sensor's "
                   "noise_sigma or snr_db, or leave the noise unstated to have it estimated")
    if math.isnan(c.hull_fill) and not coarse:
        out.append("the dips bound no region on the grid (each dip's non-empty slabs exclude the others'): the "
                   "directions, start heights or slab thickness do not belong to these profiles")
    elif c.hull_fill > HULL_FILL_MAX and not coarse:
        out.append(f"the dips measure {c.measured_volume_mm3:.4g} {c.volume_unit}, "
                   f"{c.hull_fill:.0%} of the region they bound, "
                   "which can hold at most all of it: the volumes are too large for their slabs (a level or "
                   "cross-section unit too small, levels in cm read as mm), or the dips' heights or directions are "
                   "not theirs (a wrong rig geometry or start heights)")
    if c.hull_fill < c.hull_fill_min and not coarse:  # NaN compares False
        out.append(f"the dips measure {c.measured_volume_mm3:.4g} {c.volume_unit}, "
                   f"{c.hull_fill:.2%} of the region they bound "
                   f"(real objects fill 4-76 %): a volume ten times too small, as levels in cm under a column that "
                   "says mm or a cross-section in cm^2 give, or an object much thinner than that region (a wire, a "
                   "sheet); check the level unit and the tank's cross-section")
    if abs(c.volume_ratio - 1) > c.volume_limit:
        out.append(f"the reconstruction holds {c.reconstructed_volume_mm3:.4g} {c.volume_unit}, the dips measure "
                   f"{c.measured_volume_mm3:.4g} {c.volume_unit} (ratio {c.volume_ratio:.3f}, noise explains "
                   f"+-{c.volume_ratio_noise:.3f}; continuous occupancy: "
                   f"{c.continuous_volume_mm3:.4g} {c.volume_unit}){_volume_hint(c)}")
    return out


def _volume_hint(c: Consistency) -> str:
    """Why the binary shape's volume is off when its occupancy's is not, as the tail of the volume finding: the
    threshold's hint (:func:`_binary_hint`), unless the binary shape's residual finding carries it already (else
    ``""``). At a coarse grid a threshold of 0.5 adds or drops the half-filled surface voxels (a ball at 24^3: +7%)."""
    continuous_ratio = c.continuous_volume_mm3 / c.measured_volume_mm3 if c.measured_volume_mm3 > 0 else math.nan
    if c.profile_residual > c.residual_limit or not abs(continuous_ratio - 1) <= c.volume_limit:  # NaN: no hint
        return ""
    return _binary_hint(c)


def _refit_findings(c: Consistency, refit: dict) -> list[str]:
    """A message when the surface refitted to the dips (``refit``: ``info["surface_refit"]`` of
    :mod:`dipnet.solvers.surface_refit`; the exported and scored mesh) encloses a volume further from the measured
    one than ``c`` allows the binary result (:attr:`Consistency.volume_limit`): the binary result's checks do not
    speak for it."""
    ratio = float(refit.get("volume_ratio", math.nan)) if refit.get("applied") else math.nan
    if not abs(ratio - 1) > c.volume_limit:  # NaN: no refitted surface
        return []
    return [f"the surface refitted to the dips (the exported mesh, solver.surface_refit) encloses "
            f"{refit['mesh_volume_mm3']:.4g} {c.volume_unit}, {ratio:.3f} x the measured volume (the binary result: "
            f"{c.volume_ratio:.3f}; allowed +-{c.volume_limit:.3f}): the refit moved the surface off the data's "
            "volume; "
            "use the voxel result (reconstruction.npz) or solve with solver.surface_refit=null"]


def _binary_hint(c: Consistency) -> str:
    """Why a binary shape misses its data, as the tail of its finding, when its occupancy explains the data (else
    ``""``): the threshold lost or added a shape's partial voxels (raise resolution), or it cut a smeared field
    (:func:`_smear_evidence`: more resolution would not help)."""
    if c.profile_residual_continuous > c.residual_limit:
        return ""
    evidence = _smear_evidence(c)
    if not evidence:
        return (": the occupancy explains the data and its thresholded shape does not, so the threshold loses or adds "
                "the material (as it does for parts thinner than about a voxel): raise resolution, or use the "
                "occupancy in reconstruction.npz")
    return (f": the occupancy explains the data as a smeared field, not as a shape's partial voxels "
            f"({'; '.join(evidence)}), so more resolution would not help: the dips are too few to pin a shape down "
            "without priors, or the solve stopped short of one: add dips, use a solver whose priors drive the "
            "occupancy to 0 or 1 (solver=voxel), or check the solver's settings (prior weights, iterations)")


def _smear_evidence(c: Consistency) -> list[str]:
    """What shows an occupancy to be a smeared field rather than a shape's partial voxels, in words: the threshold's
    change deep inside the regions it changes (above :data:`SMEAR_DEPTH_MAX`), a binary volume more than
    :data:`THRESHOLD_GAIN_MAX` times the occupancy's; empty when neither."""
    out = []
    if c.threshold_change_depth > SMEAR_DEPTH_MAX:  # NaN compares False
        out.append(f"{c.threshold_change_depth:.0%} of what its threshold changes lies more than a voxel deep, where "
                   "a shape's partial voxels make a layer about one voxel thick")
    if c.continuous_volume_mm3 > 0 and c.reconstructed_volume_mm3 > THRESHOLD_GAIN_MAX * c.continuous_volume_mm3:
        out.append(f"its thresholded shape holds {c.reconstructed_volume_mm3 / c.continuous_volume_mm3:.1f} times "
                   "its volume, where a threshold of 0.5 at most doubles a shape's partial voxels")
    return out
