"""A run's metrics in words (dipnet.outputs.summary): the three first answers, the short job line, every
metric grouped once with a label."""

from __future__ import annotations

from dipnet.outputs import summary
from dipnet.outputs.summary import headline

from sweep_fixtures import METRICS


def test_the_three_answers_and_a_short_headline():
    found = {a.question: a for a in summary.answers(METRICS)}
    assert found["How close to the truth?"].headline == "IoU 0.969"
    assert "0.40%" in found["How close to the truth?"].detail
    assert found["How consistent with its data?"].headline == "residual 5.9% (noise 2.3%)"
    assert "1.059" in found["How consistent with its data?"].detail
    assert found["How sure?"].headline == "26% uncertain"
    assert [a.question for a in summary.answers({"profile_residual": 0.1})] == ["How consistent with its data?"]
    line = summary.headline(METRICS)
    assert len(line) < 160 and "IoU 0.969" in line and "inconsistent" in line


def test_every_metric_is_grouped_once_with_a_label():
    groups = summary.grouped(METRICS)
    keys = [key for rows in groups.values() for _, key, _ in rows]
    assert sorted(keys) == sorted(METRICS)
    assert list(groups)[0] == "how close to the truth" \
        and ("some new metric", "some_new_metric", 1.5) in groups["other"]


def test_the_job_line_keeps_the_headline_numbers_in_order():
    line = headline({"seconds": 1.23456, "iou": 0.912345, "other": 3, "consistency": "consistent"})
    assert line == "IoU 0.912, 1.2 s, consistent"


def test_an_undefined_iou_is_said_with_its_reason_not_printed_as_a_score():
    """Before: a run whose truth had no voxel inside printed ``IoU 1.000`` (and ``uncertain nan``)."""
    reason = "the truth is thinner than a voxel at this resolution (24 voxels of 5.71 mm per axis) or off the grid"
    metrics = {"iou": float("nan"), "overlap_undefined": reason, "uncertain_fraction": float("nan"), "seconds": 1.3}
    assert headline(metrics) == f"IoU undefined ({reason}), 1.3 s"
    assert headline({**metrics, "iou": None}) == f"IoU undefined ({reason}), 1.3 s"  # as read from metrics.json
    found = {a.question: a for a in summary.answers(metrics)}
    assert found["How close to the truth?"].headline == "IoU undefined" \
        and found["How close to the truth?"].detail == reason


def test_prior_weights_and_their_reason_go_into_the_metrics():
    info = {"solver": "voxel", "prior_weights": {"tv": 2.4e-3},
            "weight_rule": {"rule": "discrepancy", "reason": "the weight expected to bring the residual to tau "
                            "times the noise", "noise_residual": 0.029, "target_residual": 0.020,
                            "residual_reached": 0.019, "noise_source": "sigma", "first_residual": 0.017}}
    flat = summary.prior_weight_metrics(info)
    assert flat == {"prior_weights": {"tv": 2.4e-3}, "prior_weight_rule": "discrepancy",
                    "prior_weight_reason": info["weight_rule"]["reason"], "prior_weight_noise_residual": 0.029,
                    "prior_weight_target_residual": 0.020, "prior_weight_residual_reached": 0.019,
                    "prior_weight_noise_source": "sigma"}
    assert list(summary.grouped(flat)) == ["run"]
    assert summary.prior_weight_metrics({"solver": "voxel", "prior_weights": {"tv": 1e-3},
                                         "weight_rule": {"rule": "fixed"}}) == {
        "prior_weights": {"tv": 1e-3}, "prior_weight_rule": "fixed"}
    assert summary.prior_weight_metrics({"solver": "minnorm"}) == {}
    assert summary.prior_weight_metrics({"threshold_rule": {"rule": "volume", "level": 0.46}}) == {
        "threshold_rule": "volume"}
    kept = {"weights": "denoiser64_tilt35", "reason": "the dips leave 55 deg about the horizontal unmeasured; ..."}
    assert summary.prior_weight_metrics({"learned_weights": [kept]}) == {
        "learned_weights": ["denoiser64_tilt35"], "learned_weights_reason": [kept["reason"]]}
    warned = "the learned prior's denoiser (denoiser64) was trained on 41 dips ...; these are 6: ..."
    flat = summary.prior_weight_metrics({"learned_prior_warnings": [warned]})
    assert flat == {"learned_prior_warnings": [warned]} and list(summary.grouped(flat)) == ["run"]
    consistent = {"profile_residual": 0.01, "profile_residual_expected": 0.012, "consistency": "consistent"}
    assert summary.LEARNED_PRIOR_WARNED not in summary.headline(consistent)
    assert summary.headline({**consistent, **flat}).endswith("consistent, " + summary.LEARNED_PRIOR_WARNED)
    detail = summary.answers({**consistent, **flat})[0].detail
    assert detail == "verdict: consistent; " + summary.LEARNED_PRIOR_WARNED  # the verdict is not read alone


def test_the_plug_and_play_rounds_and_why_they_ended_go_into_the_metrics():
    info = {"solver": "voxel", "rounds": {"done": 1, "max": 4, "rule": "discrepancy", "stopped": True,
                                          "reason": "the data term exceeds rounds_tau^2 x the noise's"}}
    flat = summary.prior_weight_metrics(info)
    assert flat == {"prior_rounds": "1 of 4", "prior_rounds_reason": info["rounds"]["reason"]}
    assert list(summary.grouped(flat)) == ["run"]
    assert summary.prior_weight_metrics({"rounds": {"done": 3, "max": 3, "rule": "fixed"}}) == \
        {"prior_rounds": "3 of 3"}


def test_the_surface_refit_and_its_mesh_go_into_the_metrics():
    refitted = {"surface_refit": {"applied": True, "reason": "the held-out dips' misfit fell by 31.0% in the probe",
                                  "residual_before": 0.012, "residual_after": 0.0015, "mesh_volume_mm3": 5210.0,
                                  "volume_ratio": 0.998}}
    flat = summary.surface_refit_metrics(refitted)
    assert flat == {"surface_refit": "refitted", "surface_refit_reason": refitted["surface_refit"]["reason"],
                    "surface_residual": 0.0015, "surface_volume_mm3": 5210.0, "surface_volume_ratio": 0.998}
    assert list(summary.grouped(flat)) == ["run"]
    kept = {"surface_refit": {"applied": False, "reason": "fell by 2.0%, less than min_gain=0.1",
                              "residual_before": 0.03, "mesh_volume_mm3": 5100.0, "volume_ratio": 0.98}}
    assert summary.surface_refit_metrics(kept)["surface_refit"] == "kept"
    assert summary.surface_refit_metrics(kept)["surface_residual"] == 0.03  # the kept surface's own
    assert summary.surface_refit_metrics({"solver": "voxel"}) == {}


def test_a_2d_runs_volumes_are_labelled_as_areas():
    """2D "volumes" are areas: with ``volume_unit`` mm^2 (a 2D run's consistency check sets it) the labels say mm²."""
    rows = {key: label for rows in summary.grouped({"measured_volume_mm3": 3156.0, "volume_unit": "mm^2"}).values()
            for label, key, _ in rows}
    assert rows["measured_volume_mm3"] == "volume the dips measure (mm²)"
    rows = {key: label for rows in summary.grouped({"measured_volume_mm3": 3156.0}).values() for label, key, _ in rows}
    assert rows["measured_volume_mm3"] == "volume the dips measure (mm³)"


def test_an_empty_reconstruction_is_named_not_scored_by_its_stand_in_chamfer():
    """Before: 'done: IoU 0.000, Chamfer 1.0000, ...' and 'Chamfer distance 100.00% of the object's diagonal': the
    Chamfer of an empty result is one truth diagonal by convention, not a distance."""
    metrics = {"iou": 0.0, "chamfer": 1.0, "empty": True, "profile_residual": 1.0, "volume_ratio": 0.0, "seconds": 1.3,
               "consistency": "inconsistent"}
    assert headline(metrics) == \
        "empty reconstruction, IoU 0.000, residual 1.000, volume ratio 0.000, 1.3 s, inconsistent"
    close = {a.question: a for a in summary.answers(metrics)}["How close to the truth?"]
    assert close.headline == "empty reconstruction" and "stand-in" in close.detail
    assert headline({**metrics, "empty": False}).startswith("IoU 0.000, Chamfer 1.0000")
