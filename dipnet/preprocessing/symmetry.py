"""Symmetry duplication: a source-independent measurement step.

An object invariant under a rotation group ``G`` about its frame's origin has the same dip
profile along ``g theta`` as along ``theta`` for every ``g`` in ``G``, so each measured
profile can be copied to those directions (the paper's section 5.2 does this for the three
cats). The pipeline applies it to any source (simulated or recorded) through the top-level
``symmetry`` option::

    python scripts/reconstruct.py symmetry='{n_fold: 4, mirror: true}'
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from dipnet.core.measurement import DipMeasurement
from dipnet.core.strict_json import finite_or_none
from dipnet.preprocessing.symmetry_moments import symmetry_fit


def symmetry_group(n_fold: int = 1, mirror: bool = False, mirror_azimuth_deg: float = 0.0) -> np.ndarray:
    """The rotation matrices ``(G, 3, 3)`` of the cyclic group ``C_n`` about z, or with
    ``mirror`` the dihedral group ``D_n`` (mirror planes through z, one at ``mirror_azimuth_deg``
    measured from +x towards +y; for n = 3, D3 has order 6)."""
    if int(n_fold) < 1:
        raise ValueError(f"n_fold must be >= 1, got {n_fold}")
    mats = []
    for i in range(int(n_fold)):
        a = 2 * math.pi * i / n_fold
        mats.append(np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]]))
    if mirror:
        p = 2 * math.radians(mirror_azimuth_deg)
        m = np.array([[math.cos(p), math.sin(p), 0], [math.sin(p), -math.cos(p), 0], [0, 0, 1.0]])
        mats += [r @ m for r in mats]
    return np.stack(mats)


def _merge(directions: np.ndarray, profiles: np.ndarray, groups_of: np.ndarray, tol_deg: float):
    """Merge directions closer than ``tol_deg`` (averaging their profiles); returns arrays and counts."""
    keep_dirs, keep_prof, counts = [], [], []
    cos_tol = math.cos(math.radians(tol_deg))
    for d, p in zip(directions, profiles):
        for j, e in enumerate(keep_dirs):
            if float(d @ e) >= cos_tol:
                keep_prof[j] = keep_prof[j] + p
                counts[j] += 1
                break
        else:
            keep_dirs.append(d)
            keep_prof.append(p.copy())
            counts.append(1)
    prof = np.stack(keep_prof) / np.asarray(counts, dtype=np.float64)[:, None]
    return np.stack(keep_dirs), prof, np.asarray(counts)


def expand_symmetry(measurement: DipMeasurement, group: np.ndarray, tol_deg: float = 0.5) -> DipMeasurement:
    """Copy every profile to the directions ``g theta`` for ``g`` in ``group`` ``(G, 3, 3)``.

    Valid when the object is invariant under the group about the frame's origin, which must lie
    on the symmetry axis (heights ``t`` along ``g theta`` of the image equal those along
    ``theta``, so profiles and offsets are unchanged). Directions within ``tol_deg`` of each
    other (including measured repeats) are merged and their profiles averaged.

    ``metadata["measured_orientations"]`` counts the dips measured: those of ``measurement``, or the count its
    metadata already holds when it was expanded before (a job's ``measurement.npz`` read back with the symmetry
    declared again: its images were not dipped). ``metadata["symmetry_fit"]`` holds how well the group fits the
    measured dips' moments (:func:`~dipnet.preprocessing.symmetry_moments.symmetry_fit`, NaNs as ``None``; kept
    from the earlier expansion when there was one), which the consistency check reads.
    """
    m = measurement
    if m.ndim != 3:
        raise ValueError("symmetry expansion is for 3D measurements")
    if not np.allclose(m.offsets.numpy(), m.offsets[0].item()):
        raise ValueError("symmetry expansion needs profiles on common slabs (equal offsets)")
    fit = m.metadata.get("symmetry_fit") if "symmetry_group_order" in m.metadata else None
    if fit is None:
        fit = finite_or_none(symmetry_fit(m, np.asarray(group, dtype=np.float64)).metrics())
    d = m.directions.numpy() / np.linalg.norm(m.directions.numpy(), axis=1, keepdims=True)
    images = np.einsum("gij,kj->gki", np.asarray(group, dtype=np.float64), d).reshape(-1, 3)
    profiles = np.tile(m.profiles.numpy(), (len(group), 1))
    dirs, prof, counts = _merge(images, profiles, None, tol_deg)
    sigma = None
    if m.sigma is not None:
        _, sig, _ = _merge(images, np.tile(m.sigma.numpy(), (len(group), 1)), None, tol_deg)
        sigma = sig / np.sqrt(counts)[:, None]
    return DipMeasurement(dirs, prof, m.slab_thickness, np.full(len(dirs), m.offsets[0].item()), sigma,
                          {**m.metadata, "symmetry_group_order": int(len(group)),
                           "measured_orientations": int(m.metadata.get("measured_orientations", m.n_orientations)),
                           "symmetry_orientations": int(len(dirs)), "symmetry_fit": fit})


def apply_symmetry(measurement: DipMeasurement, spec: Mapping | None) -> DipMeasurement:
    """:func:`expand_symmetry` with ``spec = {n_fold, mirror, mirror_azimuth_deg, tol_deg}``
    (see :func:`symmetry_group`); ``None`` or empty returns ``measurement`` unchanged."""
    if not spec:
        return measurement
    options = dict(spec)
    unknown = set(options) - {"n_fold", "mirror", "mirror_azimuth_deg", "tol_deg"}
    if unknown:
        raise ValueError(f"unknown symmetry option(s) {sorted(unknown)}; "
                         "use n_fold, mirror, mirror_azimuth_deg, tol_deg")
    tol = float(options.pop("tol_deg", 0.5))
    return expand_symmetry(measurement, symmetry_group(**options), tol)
