"""A run's metrics in words: the three answers a person asks first, a short log line, and the
full ``metrics.json`` grouped and labelled for the report.

The three answers (:func:`answers`):

* **how close** to the truth (when a truth exists): IoU and Chamfer distance;
* **how consistent** with its own data: the profile residual against what noise explains, and
  the reconstructed volume against the measured one;
* **how sure**: the share of the reconstruction whose binary call is uncertain and the
  expected error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

#: ``metric key: (group, label in words)``; keys not listed go to the group "other".
METRIC_LABELS: dict[str, tuple[str, str]] = {
    "status": ("run", "status"),
    "solver": ("run", "solver"),
    "seed": ("run", "random seed"),
    "dips_percent": ("run", "dips as % of a square system"),
    "operator": ("run", "operator backend"),
    "seconds": ("run", "solve time (s)"),
    "n_dips": ("run", "number of dips"),
    "n_dips_measured": ("run", "dips measured (n_dips less the images of a declared symmetry)"),
    "resolution": ("run", "voxels per axis"),
    "ndim": ("run", "dimensions"),
    "shape": ("run", "shape"),
    "snr_db": ("run", "level-sensor SNR (dB; none: noise-free)"),
    "frame_offset_mm": ("run", "mesh files: grid frame + this shift = your file's frame (mm; 2D: on frame_axes)"),
    "frame_axes": ("run", "2D from a mesh: the axes of your file that the 2D x, y are"),
    "frame_scale": ("run", "mesh files: mm per unit of your file (divide their vertices by it for its units)"),
    "prior_weights": ("run", "prior weights used by the solver"),
    "prior_weight_rule": ("run", "how the prior weights were set (fixed: from the config)"),
    "prior_weight_reason": ("run", "why that weight"),
    "prior_weight_noise_residual": ("run", "weight rule: relative residual of the noise alone"),
    "prior_weight_target_residual": ("run", "weight rule: residual aimed at (tau x the noise's)"),
    "prior_weight_residual_reached": ("run", "weight rule: residual of the result"),
    "prior_weight_noise_source": ("run", "weight rule: noise from the measurement's sigma (stated), the readings' own "
                                  "scatter, or estimated from the profiles"),
    "noise_model": ("run", "how the data term weighed the slabs' errors: independent, or correlated (differences of "
                    "cumulative readings; smoothed profiles count as independent)"),
    "prior_rounds": ("run", "plug-and-play rounds run, of the most allowed"),
    "prior_rounds_reason": ("run", "why the rounds ended there"),
    "surface_refit": ("run",
                      "the surface refitted to the dips as a mesh (refitted), or the voxel result's kept (kept)"),
    "surface_refit_reason": ("run", "why (the held-out dips' misfit in the refit's probe)"),
    "surface_residual": ("run", "relative residual of the refit's mesh's exact dips (refitted, or the result's own "
                                "surface on the data grid when kept)"),
    "surface_volume_mm3": ("run", "volume enclosed by the refit's mesh (mm^3; the exported one unless the surface was "
                                  "kept and the solver's finer sampling is exported: solver.output_upsample)"),
    "surface_volume_ratio": ("run", "the refit's mesh's volume over the measured one (the profiles' median total)"),
    "learned_weights": ("run", "learned prior: the weights kept of its candidates (by the dips' plan)"),
    "learned_weights_reason": ("run", "why those weights"),
    "learned_prior_warnings": ("run", "learned prior: dips or an object unlike its training ones (a consistent "
                                      "verdict does not speak for what it filled in)"),
    "threshold": ("run", "occupancy level of the binary shape and its surface"),
    "overrides": ("run", "command-line overrides of the run that wrote these metrics"),
    "threshold_rule": ("run", "how that level was set (volume: its surface encloses the measured volume)"),
    "iou": ("how close to the truth", "intersection over union (1 = identical)"),
    "chamfer": ("how close to the truth", "Chamfer distance (fraction of the truth's diagonal)"),
    "hausdorff": ("how close to the truth", "Hausdorff distance (fraction of the truth's diagonal)"),
    "volume_error": ("how close to the truth", "volume error (relative to the exact volume)"),
    "false_positive": ("how close to the truth", "extra voxels (fraction of the truth's voxels)"),
    "false_negative": ("how close to the truth", "missed voxels (fraction of the truth's voxels)"),
    "empty": ("how close to the truth", "reconstruction empty"),
    "overlap_undefined": ("how close to the truth", "why IoU and the false rates are undefined"),
    "truth_voxel_volume_error": ("how close to the truth", "truth voxelisation: partial-volume error"),
    "truth_binary_volume_error": ("how close to the truth", "truth voxelisation: binary volume error"),
    "truth_level": ("how close to the truth", "truth occupancy counted as inside"),
    "profile_residual": ("how consistent with the data", "profile residual (relative)"),
    "profile_residual_continuous": ("how consistent with the data", "profile residual of the continuous occupancy"),
    "profile_residual_expected": ("how consistent with the data", "residual that noise and voxels explain"),
    "residual_limit": ("how consistent with the data", "residual limit of the check"),
    "noise_source": ("how consistent with the data", "where the noise level comes from: sigma (stated), readings "
                     "(the readings' own scatter) or estimated (from the profiles)"),
    "measured_volume_mm3": ("how consistent with the data", "volume the dips measure (mm³)"),
    "reconstructed_volume_mm3": ("how consistent with the data",
                                 "volume of the reconstruction's inside voxels (mm³; its mesh rounds their corners)"),
    "continuous_volume_mm3": ("how consistent with the data", "volume of the continuous occupancy (mm³)"),
    "threshold_change_depth": ("how consistent with the data",
                               "share of the threshold's change deeper than a voxel (above 0.04: a smeared occupancy)"),
    "volume_ratio": ("how consistent with the data", "reconstructed / measured volume"),
    "volume_ratio_noise": ("how consistent with the data", "volume ratio that noise explains (±)"),
    "volume_limit": ("how consistent with the data", "volume-ratio limit of the check"),
    "grid_volume_fraction": ("how consistent with the data", "share of the measured volume on the grid"),
    "volume_unit": ("how consistent with the data", "unit of the volumes (mm^2 in 2D: areas)"),
    "hull_fill": ("how consistent with the data", "measured volume / region the dips bound"),
    "hull_fill_min": ("how consistent with the data", "hull-fill limit of the check (a unit mistake below)"),
    "height_trend_pivot_mm": ("how consistent with the data", "height trend: pivot offset (mm)"),
    "height_trend_offset_mm": ("how consistent with the data", "height trend: level offset (mm)"),
    "height_trend_limit_mm": ("how consistent with the data", "height trend limit (mm)"),
    "profile_floor_mm3": ("how consistent with the data", "volume every slab holds where it should be empty (mm³)"),
    "profile_floor_share": ("how consistent with the data", "that floor's share of the measured volume"),
    "profile_floor_limit_mm3": ("how consistent with the data", "floor limit (mm³)"),
    "level_fall_share": ("how consistent with the data", "share of the volume a falling level takes over a dip"),
    "level_fall_sigmas": ("how consistent with the data", "the fall in standard errors"),
    "reading_noise_mm3": ("how consistent with the data", "noise of one reading the readings show (mm³)"),
    "reading_noise_ratio": ("how consistent with the data",
                            "stated noise / the readings' own (flagged above 3 or below 1/3)"),
    "reading_noise_leak": ("how consistent with the data",
                           "the readings' noise estimate at twice the step over it (below 2: noise alone)"),
    "dip_outliers": ("how consistent with the data", "dips that disagree with the others (counted from 0)"),
    "dip_agreement_tested": ("how consistent with the data", "dips the agreement test judged (0: not tested)"),
    "symmetry_declared": ("how consistent with the data",
                          "symmetry tested: images (the symmetry option) or prior (the solver's)"),
    "symmetry_misfit": ("how consistent with the data",
                        "its misfit to the dips' moments (share of the radius of gyration)"),
    "symmetry_misfit_p": ("how consistent with the data", "that misfit's significance (p-value)"),
    "symmetry_misfit_order": ("how consistent with the data", "moment order of that misfit"),
    "symmetry_misfit_limit": ("how consistent with the data", "misfit limit (rejected above it with p < 0.001)"),
    "symmetry_rejected": ("how consistent with the data", "the dips reject the declared symmetry"),
    "outside_share": ("how consistent with the data", "largest share of a dip's volume beyond the slabs"),
    "outside_limit": ("how consistent with the data", "limit of that share"),
    "object_reach_mm": ("how consistent with the data",
                        "how far from the grid's centre the dips show the object reaching (mm)"),
    "working_radius_mm": ("how consistent with the data",
                          "the working ball's radius, which that reach must not pass (mm)"),
    "floor_beyond_ratio": ("how consistent with the data",
                           "readings beyond the slabs over what a drift of the floor puts there"),
    "quantum_volume_mm3": ("how consistent with the data", "volume of one step of the sensor's reading (mm³)"),
    "mean_slab_mm3": ("how consistent with the data", "mean slab the object fills (mm³)"),
    "consistency": ("how consistent with the data", "verdict"),
    "consistency_warnings": ("how consistent with the data", "findings"),
    "plan_warning": ("how consistent with the data", "what the dips' plan leaves unmeasured"),
    "underdetermined": ("how consistent with the data", "why the dips are too few to determine a shape (the verdict "
                        "underdetermined)"),
    "uncertainty_mean": ("how sure", "mean posterior (or ensemble) std over the support"),
    "uncertain_fraction": ("how sure", "share of the support with P(wrong) > 0.2"),
    "expected_error_fraction": ("how sure", "expected wrong voxels / reconstructed voxels"),
    "error_rate_by_uncertainty_decile": ("how sure", "true error rate per uncertainty decile (least to most)"),
    "error_rate_where_sure": ("how sure", "true error rate of the voxels with P(wrong) < 0.05"),
    "uncertainty_method": ("how sure", "uncertainty method (linearised posterior or samples)"),
    "uncertainty_brier": ("how sure", "Brier score of the occupancy probability"),
    "uncertainty_samples": ("how sure", "ensemble members"),
    "uncertainty_noise_std": ("how sure", "noise added to each member's slabs (mm³)"),
    "uncertainty_seconds": ("how sure", "time of the ensemble (s)"),
    "missing_cone_deg": ("what the plan resolves", "missing cone (deg)"),
    "mean_direction_gap_deg": ("what the plan resolves", "mean angle to the nearest dip (deg)"),
    "frequency_coverage": ("what the plan resolves", "covered share of the frequency ball"),
    "polar_coverage": ("what the plan resolves", "polar coverage"),
    "azimuthal_coverage": ("what the plan resolves", "azimuthal coverage"),
    "resolvability_diameter_mm": ("what the plan resolves", "diameter of the resolvable ball (mm)"),
    "azimuthal_signal_ratio": ("what the plan resolves", "azimuthal signal ratio"),
    "readings_repaired": ("data checks", "readings repaired"),
    "readings_flagged": ("data checks", "flagged readings left out"),
    "dips_rejected": ("data checks", "dips rejected"),
    "dips_truncated_dropped": ("data checks", "truncated dips dropped"),
    "dips_incomplete_dropped": ("data checks", "incomplete dips left out (an interrupted scan)"),
    "validation_warnings": ("data checks", "validation warnings"),
    "validation": ("data checks", "validation details"),
}

GROUPS = ("how close to the truth", "how consistent with the data", "how sure", "what the plan resolves",
          "data checks", "run", "other")


@dataclass
class Answer:
    """One of the three first answers: a question, its headline and a sentence of detail."""

    question: str
    headline: str
    detail: str


LEARNED_PRIOR_WARNED = ("the learned prior warned that these dips or this object are unlike its training ones "
                        "(learned_prior_warnings): a consistent verdict does not speak for what it filled in")
"""What the answers and the headline add when ``metrics.json`` holds ``learned_prior_warnings``."""


def _num(metrics: dict[str, Any], key: str) -> float | None:
    """``metrics[key]`` as a float; ``None`` when absent, not a number, or undefined (NaN, null)."""
    value = metrics.get(key)
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    return float(value) if number and math.isfinite(value) else None


def answers(metrics: dict[str, Any]) -> list[Answer]:
    """How close (IoU, Chamfer; only with a truth), how consistent (residual vs noise, volume
    ratio), how sure (uncertain share, expected error), from a run's ``metrics.json``."""
    out = []
    iou, chamfer = _num(metrics, "iou"), _num(metrics, "chamfer")
    if iou is not None and metrics.get("empty") is True:
        out.append(Answer("How close to the truth?", "empty reconstruction",
                          "no shape came out of the solve: no surface to measure (its Chamfer distance of one "
                          "diagonal is a stand-in)"))
    elif iou is not None:
        out.append(Answer("How close to the truth?", f"IoU {iou:.3f}",
                          f"Chamfer distance {100 * chamfer:.2f}% of the object's diagonal" if chamfer is not None
                          else "no surface distance"))
    elif metrics.get("overlap_undefined"):
        out.append(Answer("How close to the truth?", "IoU undefined", str(metrics["overlap_undefined"])))
    residual, expected = _num(metrics, "profile_residual"), _num(metrics, "profile_residual_expected")
    ratio = _num(metrics, "volume_ratio")
    if residual is not None:
        head = f"residual {100 * residual:.1f}%"
        if expected is not None:
            head += f" (noise {100 * expected:.1f}%)"
        parts = [] if ratio is None else [f"reconstructed volume {ratio:.3f} × the measured"]
        if metrics.get("consistency"):
            parts.append(f"verdict: {metrics['consistency']}")
        if metrics.get("learned_prior_warnings"):
            parts.append(LEARNED_PRIOR_WARNED)
        out.append(Answer("How consistent with its data?", head,
                          "; ".join(parts) or "profile residual relative to the measured profiles"))
    uncertain, expected_error = _num(metrics, "uncertain_fraction"), _num(metrics, "expected_error_fraction")
    if uncertain is not None:
        detail = f"{100 * uncertain:.0f}% of the object's voxels have P(wrong) > 0.2"
        if expected_error is not None:
            detail += f"; expected wrong voxels {100 * expected_error:.0f}% of its volume"
        out.append(Answer("How sure?", f"{100 * uncertain:.0f}% uncertain", detail))
    return out


def headline(metrics: dict[str, Any]) -> str:
    """The few numbers of :func:`answers` (and the solve time) for a short log line; an empty reconstruction is
    named first, without its stand-in Chamfer distance."""
    empty = metrics.get("empty") is True
    parts = ["empty reconstruction"] if empty else []
    for key, fmt in (("iou", "IoU {:.3f}"), ("chamfer", "Chamfer {:.4f}"), ("profile_residual", "residual {:.3f}"),
                     ("volume_ratio", "volume ratio {:.3f}"), ("uncertain_fraction", "uncertain {:.2f}"),
                     ("seconds", "{:.1f} s")):
        value = _num(metrics, key)
        if empty and key == "chamfer":
            continue
        if value is not None:
            parts.append(fmt.format(value))
        elif key == "iou" and metrics.get("overlap_undefined"):
            parts.append(f"IoU undefined ({metrics['overlap_undefined']})")
    if metrics.get("consistency"):
        parts.append(str(metrics["consistency"]))
    if metrics.get("learned_prior_warnings"):
        parts.append(LEARNED_PRIOR_WARNED)
    return ", ".join(parts)


def prior_weight_metrics(info: dict[str, Any]) -> dict[str, Any]:
    """The prior weights a solver used and why, from its ``Reconstruction.info``
    (``prior_weights`` and ``weight_rule``, see :mod:`dipnet.solvers.weights`; ``rounds``, see
    :class:`~dipnet.solvers.voxel.VoxelSolver`; ``threshold_rule``, ``learned_weights``, ``learned_prior_warnings``
    and ``noise_model``, see
    :class:`~dipnet.solvers.optimize.OptimisationSolver`), as flat ``metrics.json`` entries; ``{}`` for
    solvers without priors."""
    out: dict[str, Any] = {}
    if "prior_weights" in info:
        out["prior_weights"] = dict(info["prior_weights"])
    rule = info.get("weight_rule") or {}
    if rule:
        out["prior_weight_rule"] = rule["rule"]
    for key in ("reason", "noise_residual", "target_residual", "residual_reached", "noise_source"):
        if key in rule:
            out[f"prior_weight_{key}"] = rule[key]
    rounds = info.get("rounds") or {}
    if rounds:
        out["prior_rounds"] = f"{rounds['done']} of {rounds['max']}"
    if "reason" in rounds:
        out["prior_rounds_reason"] = rounds["reason"]
    if "threshold_rule" in info:
        out["threshold_rule"] = info["threshold_rule"]["rule"]
    if "noise_model" in info:
        out["noise_model"] = info["noise_model"]
    choices = info.get("learned_weights") or []
    if choices:
        out["learned_weights"] = [choice["weights"] for choice in choices]
        out["learned_weights_reason"] = [choice["reason"] for choice in choices]
    if info.get("learned_prior_warnings"):
        out["learned_prior_warnings"] = list(info["learned_prior_warnings"])
    return out


def surface_refit_metrics(info: dict[str, Any]) -> dict[str, Any]:
    """Whether the result's surface was refitted to the dips and why, the exported mesh's relative residual and
    volume (mm^3), from ``info["surface_refit"]`` (:mod:`dipnet.solvers.surface_refit`), as flat ``metrics.json``
    entries; ``{}`` when the solver has no refit. The residual is the refitted mesh's, or, when the surface was
    kept, the voxel result's own surface's (before any refit)."""
    record = info.get("surface_refit")
    if not record:
        return {}
    out = {"surface_refit": "refitted" if record.get("applied") else "kept", "surface_refit_reason": record["reason"]}
    residual = record.get("residual_after", record.get("residual_before"))
    if residual is not None:
        out["surface_residual"] = residual
    if "mesh_volume_mm3" in record:
        out["surface_volume_mm3"] = record["mesh_volume_mm3"]
        out["surface_volume_ratio"] = record["volume_ratio"]
    return out


def grouped(metrics: dict[str, Any]) -> dict[str, list[tuple[str, str, Any]]]:
    """``{group: [(label in words, key, value), ...]}`` in :data:`GROUPS` order, empty groups left out; volumes
    labelled mm² when the run's ``volume_unit`` is ``mm^2`` (2D: its "volumes" are areas)."""
    out: dict[str, list[tuple[str, str, Any]]] = {g: [] for g in GROUPS}
    areas = metrics.get("volume_unit") == "mm^2"
    for key, value in metrics.items():
        group, label = METRIC_LABELS.get(key, ("other", key.replace("_", " ")))
        label = label.replace("mm³", "mm²") if areas else label
        out[group].append((label, key, value))
    return {g: rows for g, rows in out.items() if rows}
