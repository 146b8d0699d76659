"""Symmetry duplication is a pipeline step for any source (here: simulated dips)."""

from __future__ import annotations

import math

import pytest
from hydra import compose, initialize_config_module

from dipnet.jobs.pipeline import run
from dipnet.preprocessing.symmetry import apply_symmetry


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
    import torch

    from dipnet.core.orientations import fibonacci_hemisphere
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
