"""output.uncertainty=samples: the ensemble's maps in the run directory, metrics and bad values."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from dipnet.jobs.options import ConfigError
from dipnet.jobs.pipeline import run


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=["output.progress=false", "output.resolvability=false",
                                                        "threads=1", *overrides])


def test_a_job_writes_the_ensemble_probability(tmp_path):
    result = run(_cfg("resolution=16", "n_dips=12", "solver=voxel", "solver.iterations=60", "output.mesh_formats=[]",
                      "output.uncertainty=samples", "output.uncertainty_samples=2", "output.uncertainty_iterations=0.5",
                      "output.figures=false"), tmp_path)
    with np.load(tmp_path / "reconstruction.npz") as saved:
        p, p_wrong = saved["uncertainty_probability"], saved["uncertainty_p_wrong"]
        assert p.shape == (16, 16, 16) and 0 <= p.min() and p.max() <= 1
        assert saved["uncertainty_std"].shape == (16, 16, 16) and p_wrong.max() <= 1
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["uncertainty_method"] == "samples" and metrics["uncertainty_samples"] == 2
    assert 0 <= metrics["uncertainty_brier"] < 0.25 and len(metrics["error_rate_by_uncertainty_decile"]) == 10
    assert result.metrics["uncertainty_method"] == "samples"


@pytest.mark.parametrize("override, message", [("output.uncertainty=often", "output.uncertainty must be"),
                                               ("output.uncertainty_samples=1", "uncertainty_samples"),
                                               ("output.uncertainty_iterations=0", "uncertainty_iterations")])
def test_bad_uncertainty_options_are_named(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        run(_cfg(override), tmp_path)
