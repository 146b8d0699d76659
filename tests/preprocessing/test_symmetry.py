"""Symmetry duplication is a pipeline step for any source (here: simulated dips)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from analytic_profiles import ball_measurement
from hydra import compose, initialize_config_module

from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.jobs.pipeline import run
from dipnet.preprocessing.symmetry import MAX_MERGE_DEG, apply_symmetry


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=["output.progress=false", "output.figures=false", *overrides])


def test_simulated_job_duplicates_profiles_under_the_declared_group(tmp_path):
    plain = run(_cfg("resolution=16", "n_dips=6", "shape.name=ball"), tmp_path / "plain")
    sym = run(_cfg("resolution=16", "n_dips=6", "shape.name=ball", "symmetry={n_fold: 4}"), tmp_path / "sym")
    assert plain.measurement.n_orientations == 6
    assert sym.measurement.n_orientations == 24 and sym.measurement.metadata["symmetry_group_order"] == 4
    assert sym.metrics["n_dips"] == 24 and sym.metrics["iou"] >= plain.metrics["iou"] - 0.01
    assert sym.metrics["symmetry_declared"] == "images" and not sym.metrics["symmetry_rejected"]  # a ball has it
    assert plain.metrics["symmetry_declared"] == "" and math.isnan(plain.metrics["symmetry_misfit"])
    assert apply_symmetry(plain.measurement, None) is plain.measurement
    with pytest.raises(ValueError, match="unknown symmetry option"):
        apply_symmetry(plain.measurement, {"nfold": 3})


def test_a_measurement_expanded_again_counts_the_dips_measured_once():
    """Before: a job's ``measurement.npz`` (10 dips x a 4-fold group = 40) read back with ``symmetry={n_fold: 4}``
    again reported ``n_dips_measured`` 40 in ``metrics.json``: the images counted as measured dips."""
    from dipnet.core.measurement import DipMeasurement

    measured = DipMeasurement(fibonacci_hemisphere(10), torch.ones(10, 8, dtype=torch.float64), 1.0,
                              torch.full((10,), -4.0))
    once = apply_symmetry(measured, {"n_fold": 4})
    twice = apply_symmetry(once, {"n_fold": 4})
    assert (once.n_orientations, twice.n_orientations) == (40, 40)
    assert once.metadata["measured_orientations"] == twice.metadata["measured_orientations"] == 10
    assert twice.metadata["symmetry_fit"] == once.metadata["symmetry_fit"]  # tested on the 10 dips, not the images
    assert once.metadata["symmetry_fit"]["dips"] == 10
    from dipnet.preprocessing.symmetry_moments import SymmetryFit

    edited = SymmetryFit.from_metadata({"misfit": None, "rejected": True, "order": 2, "note": "by hand"})
    assert math.isnan(edited.misfit) and edited.rejected and edited.order == 2 and edited.dips == 0


def test_merging_is_limited_to_directions_a_dip_repeats_at():
    """Before: ``tol_deg: 15`` averaged the profiles of distinct dips into one (a torus under ``n_fold: 4``: 34 of 120
    directions kept, IoU 0.963 -> 0.893, ``consistent``, no word). Now a tolerance above ``MAX_MERGE_DEG`` is
    refused."""
    measured = ball_measurement([0.0, 0.0, 0.0], 20.0, fibonacci_hemisphere(10).numpy())
    assert apply_symmetry(measured, {"n_fold": 4, "tol_deg": MAX_MERGE_DEG}).n_orientations >= 37
    with pytest.raises(ValueError, match=r"tol_deg must lie in \[0, 2\] deg, got 15.*average distinct dips"):
        apply_symmetry(measured, {"n_fold": 4, "tol_deg": 15})


def test_a_merged_direction_counts_its_distinct_measured_dips_in_its_noise():
    """Before: a dip along the axis of an 8-fold group merged with its 7 images to sigma / sqrt(8), as if dipped 8
    times; a measurement expanded before, read back with its group, divided its sigma again (10 dB: the residual
    limit 0.377 -> 0.189, the TV weight to its floor). Now a merge divides by the number of distinct measured dips."""
    directions = np.array([[0.0, 0.0, 1.0], [math.sin(0.5), 0.0, math.cos(0.5)], [0.0, math.sin(0.5), math.cos(0.5)]])
    measured = ball_measurement([0.0, 0.0, 0.0], 20.0, directions)
    measured.sigma = torch.full_like(measured.profiles, 2.0)
    once = apply_symmetry(measured, {"n_fold": 4})
    up = np.argmax(once.directions.numpy()[:, 2])
    assert once.n_orientations == 5  # the axis, and 4 tilted directions each reached by dips 2 and 3
    assert once.sigma[up].unique().tolist() == [2.0]  # one dip and its own images
    tilted = [k for k in range(5) if k != up]
    assert torch.allclose(once.sigma[tilted], torch.tensor(2.0 / math.sqrt(2), dtype=torch.float64))
    twice = apply_symmetry(once, {"n_fold": 4})
    assert torch.equal(twice.sigma, once.sigma) and torch.equal(twice.profiles, once.profiles)


def test_a_measurement_read_back_under_another_group_is_tested_again():
    """Before: a ``measurement.npz`` expanded under a mirror the object has, read back with a 4-fold group it lacks,
    reused the first group's passing fit (misfit 0.0022, ``consistent``; the same 4-fold declared on the dips
    themselves: 0.023, rejected). Now the stored fit serves the same group only."""
    ball = ball_measurement([5.0, 0.0, 0.0], 20.0, fibonacci_hemisphere(41).numpy())  # off the z axis, on the xz plane
    mirrored = apply_symmetry(ball, {"mirror": True})
    assert not mirrored.metadata["symmetry_fit"]["rejected"]
    assert apply_symmetry(mirrored, {"mirror": True}).metadata["symmetry_fit"] == mirrored.metadata["symmetry_fit"]
    assert apply_symmetry(ball, {"n_fold": 4}).metadata["symmetry_fit"]["rejected"]
    assert apply_symmetry(mirrored, {"n_fold": 4, "mirror": True}).metadata["symmetry_fit"]["rejected"]


def test_a_2d_measurement_is_refused_naming_the_solvers_prior():
    """A 2D object has no vertical axis to copy dips about: the refusal names the 2D way to declare a symmetry."""
    from dipnet.core.measurement import DipMeasurement
    from dipnet.core.orientations import angles_2d, directions_2d

    m = DipMeasurement(directions_2d(angles_2d(4)), torch.ones(4, 8), 1.0, torch.full((4,), -4.0))
    with pytest.raises(ValueError, match=r"for 3D measurements .*got a 2D one: in 2D, declare the symmetry as a "
                                         r"solver prior"):
        apply_symmetry(m, {"n_fold": 2})
