"""output.checkpoint: an interrupted pipeline solve, rerun with the same settings, resumes to the
uninterrupted result."""

from __future__ import annotations

import dataclasses
import json
import warnings

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import angles_2d, directions_2d
from dipnet.operators import make_operator
from dipnet.solvers.checkpoint import Checkpoint, attach_checkpoint
from dipnet.jobs.pipeline import run
from dipnet.solvers.minnorm import MinNormSolver
from dipnet.solvers.voxel import VoxelSolver

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


def _disk_dips() -> DipMeasurement:
    """Noise-free dips of an off-centre disk on a 16^2 grid, 8 angles, with a stated noise."""
    grid = Grid(16, 2, 100.0)
    centres = grid.centers()
    disk = (((centres - torch.tensor([12.0, -6.0], dtype=centres.dtype)) ** 2).sum(-1) < 25.0**2).double()
    op = make_operator(grid, directions_2d(angles_2d(8, start_deg=10.0)), backend="splat")
    with torch.no_grad():
        profiles = op(disk)
    return DipMeasurement(op.directions, profiles, op.slab_thickness, op.slab_edges()[:1].expand(8),
                          torch.full_like(profiles, 5.0))


def _swapped(values: torch.Tensor, i: int, j: int, dim: int = 0) -> torch.Tensor:
    index = torch.arange(values.shape[dim])
    index[[i, j]] = index[[j, i]]
    return values.index_select(dim, index)


OTHER_DATA = {  # each keeps the sums the fingerprint held before: the profiles' total and the directions'
    "two dips' directions swapped": lambda m: dataclasses.replace(m, directions=_swapped(m.directions, 0, 3)),
    "two slabs swapped": lambda m: dataclasses.replace(m, profiles=_swapped(m.profiles, 6, 9, dim=1)),
    "another stated noise": lambda m: dataclasses.replace(m, sigma=_swapped(m.sigma * torch.linspace(1, 3, 8)[:, None],
                                                                            0, 7)),
}


@pytest.mark.parametrize("change", OTHER_DATA)
def test_a_checkpoint_of_other_data_with_the_same_sums_is_not_resumed(tmp_path, change):
    """The fingerprint held the sums of the profiles and of the directions: a measurement with two dips or slabs
    swapped resumed the other one's finished solve, and its result came out with exit code 0."""
    torch.set_num_threads(1)
    first = _disk_dips()
    solver = VoxelSolver(iterations=20, progress=False, seed=0)
    solver.checkpoint = Checkpoint(tmp_path, every=5)
    solver.solve(first, make_operator(Grid(16, 2, 100.0), first.directions, backend="splat"))
    other = OTHER_DATA[change](first)
    with pytest.warns(UserWarning, match="is not used: it was made for another problem"):
        solver.solve(other, make_operator(Grid(16, 2, 100.0), other.directions, backend="splat"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same data again resume: no warning
        solver.solve(other, make_operator(Grid(16, 2, 100.0), other.directions, backend="splat"))
