"""output.checkpoint: an interrupted pipeline solve, rerun with the same settings, resumes to the
uninterrupted result."""

from __future__ import annotations

import json

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.solvers.checkpoint import Checkpoint, attach_checkpoint
from dipnet.jobs.pipeline import run
from dipnet.solvers.minnorm import MinNormSolver

SMALL = ["output.progress=false", "output.figures=false", "output.uncertainty=false", "output.resolvability=false",
         "resolution=24", "n_dips=24", "shape.name=ball", "solver=voxel", "solver.iterations=80", "solver.tol=0"]


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[*SMALL, *overrides])


@pytest.mark.slow
def test_interrupted_pipeline_solve_resumes_to_the_uninterrupted_result(tmp_path, monkeypatch):
    torch.set_num_threads(1)
    reference = run(_cfg(), tmp_path / "reference").reconstruction
    written = json.loads((tmp_path / "reference" / "metrics.json").read_text())  # the TV weight and why
    assert written["prior_weight_rule"] == "discrepancy" and written["prior_weight_reason"]
    assert written["prior_weights"]["tv"] == reference.info["weight_rule"]["weight"]
    saves, restored = [], []
    original_save, original_restore = Checkpoint.save, Checkpoint.restore

    def save_then_stop(self, *args, **kwargs):  # a kill right after the 3rd write (coarse stage done, 20 fine steps)
        wrote = original_save(self, *args, **kwargs)
        saves.extend([True] if wrote else [])
        if len(saves) == 3:
            raise KeyboardInterrupt
        return wrote

    monkeypatch.setattr(Checkpoint, "save", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        run(_cfg("output.checkpoint=true", "output.checkpoint_every=20"), tmp_path / "job")
    monkeypatch.setattr(Checkpoint, "save", original_save)

    def spy_restore(self, stage, *args):
        restored.append((stage, original_restore(self, stage, *args)[0]))
        return restored[-1][1], *original_restore(self, stage, *args)[1:]

    monkeypatch.setattr(Checkpoint, "restore", spy_restore)
    resumed = run(_cfg("output.checkpoint=true", "output.checkpoint_every=20"), tmp_path / "job").reconstruction
    # coarse stage finished (24 steps), fine stage at step 20, the TV weight's refit not begun
    assert [step for _, step in restored] == [24, 20, 0]
    torch.testing.assert_close(resumed.occupancy, reference.occupancy, atol=1e-5, rtol=0)
    assert resumed.history["loss"] == pytest.approx(reference.history["loss"], rel=1e-5)


def test_checkpoint_setting_is_checked(tmp_path):
    voxel = instantiate(_cfg().solver)
    assert attach_checkpoint(voxel, None, tmp_path) is None and voxel.checkpoint is None
    assert attach_checkpoint(voxel, str(tmp_path / "ck"), tmp_path, every=5).directory == tmp_path / "ck"
    with pytest.raises(ValueError, match="output.checkpoint must be"):
        attach_checkpoint(voxel, 3, tmp_path)
    with pytest.warns(UserWarning, match="does not checkpoint"):
        assert attach_checkpoint(MinNormSolver(progress=False), True, tmp_path) is None


@pytest.mark.parametrize("where", ["file", "under_a_file", "true"])
def test_a_checkpoint_directory_that_is_a_file_is_refused_before_any_work(tmp_path, where):
    """output.checkpoint=FILE (or a folder under a file) was taken: the solve went on and warned at every checkpoint."""
    blocking = tmp_path / ("job/checkpoints" if where == "true" else "ck.pt")
    blocking.parent.mkdir(parents=True, exist_ok=True)
    blocking.write_text("not a folder")
    setting = {"file": f"'{blocking}'", "under_a_file": f"'{blocking / 'sub'}'", "true": "true"}[where]
    with pytest.raises(ValueError, match=f"output.checkpoint=.*: {blocking} is a file, not a directory"):
        run(_cfg(f"output.checkpoint={setting}"), tmp_path / "job")
    assert not (tmp_path / "job" / "measurement.npz").exists()
    assert blocking.read_text() == "not a folder"
