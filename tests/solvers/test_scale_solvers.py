"""Solvers at scale: minnorm's memory-based method choice, checkpointed and resumed optimisation."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_module

from dipnet.solvers.checkpoint import Checkpoint
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.jobs.resources import estimate_memory
from dipnet.solvers.minnorm import MinNormSolver, cholesky_bytes
from dipnet.solvers.voxel import VoxelSolver

from solver_helpers import noise_free_problem, one_thread  # noqa: F401  (fixture)


def test_minnorm_auto_goes_matrix_free_when_the_explicit_matrices_would_not_fit():
    truth, op, meas = noise_free_problem(3, None)
    rows = op.n_orientations * op.n_slabs  # 480 rows: few enough for the row rule
    assert cholesky_bytes(op) == 8 * rows**2 + 24 * op.n_orientations * 24**3
    fits = MinNormSolver(progress=False).solve(meas, op)
    limit = cholesky_bytes(op) - 1
    matrix_free = MinNormSolver(max_cholesky_bytes=limit, iter_lim=200, progress=False).solve(meas, op)
    assert fits.info["method"] == "cholesky" and matrix_free.info["method"] == "lsmr"
    # same damped least-squares problem, so nearly the same volume
    gap = (fits.occupancy - matrix_free.occupancy).norm() / fits.occupancy.norm()
    assert gap < 0.05
    # 240^3 with 5,760 dips: 15 TB for cholesky (and rows far above the row limit too)
    big = SimpleNamespace(n_orientations=5760, n_slabs=240, grid=Grid(240, 3))
    assert cholesky_bytes(big) == 8 * (5760 * 240) ** 2 + 24 * 5760 * 240**3
    assert cholesky_bytes(big) > 1e13 > MinNormSolver().max_cholesky_bytes


class _Interrupt(Checkpoint):
    """A checkpoint that stops the solve (as a kill would) right after its ``stop_after``-th save."""

    def __init__(self, directory, every: int, stop_after: int) -> None:
        super().__init__(directory, every)
        self.saves, self.stop_after = 0, stop_after

    def save(self, *args, **kwargs) -> bool:
        self.saves += super().save(*args, **kwargs)
        if self.saves >= self.stop_after:
            raise KeyboardInterrupt
        return True


def test_interrupted_voxel_solve_resumes_to_the_uninterrupted_result(tmp_path):
    truth, op, meas = noise_free_problem(3, None)
    options = {"iterations": 60, "tol": 0.0, "progress": False}
    reference = VoxelSolver(**options).solve(meas, op)
    # interrupted in the fine stage (18 coarse steps, then saves at 10, 20, ... fine steps)
    with pytest.raises(KeyboardInterrupt):
        VoxelSolver(checkpoint=_Interrupt(tmp_path, every=10, stop_after=4), **options).solve(meas, op)
    assert sorted(p.name for p in tmp_path.glob("*.pt")) == ["voxel_12_3.pt", "voxel_24_3.pt"]
    resumed = VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **options).solve(meas, op)
    torch.testing.assert_close(resumed.occupancy, reference.occupancy, atol=1e-5, rtol=0)
    assert resumed.history["loss"] == pytest.approx(reference.history["loss"], rel=1e-5)
    # a checkpoint of another problem is ignored, with a warning
    k = op.n_orientations
    other = DipMeasurement(op.directions, 2 * meas.profiles, op.slab_thickness, op.slab_edges()[:1].expand(k))
    with pytest.warns(UserWarning, match="another problem"):
        VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **options).solve(other, op)


def test_checkpoint_made_with_other_solver_options_is_not_resumed(tmp_path):
    """Before: a changed prior weight or temperature resumed the old state (its finished coarse stage
    reused), exit 0, a result that was neither the old options' nor the new ones'."""
    truth, op, meas = noise_free_problem(3, None)
    options = {"iterations": 40, "tol": 0.0, "progress": False}
    VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **options).solve(meas, op)
    changed = {**options, "priors": {"tv": {"weight": 0.05}}, "temperature_end": 1.0}
    clean = VoxelSolver(**changed).solve(meas, op)
    with pytest.warns(UserWarning) as record:
        rerun = VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **changed).solve(meas, op)
    messages = [str(w.message) for w in record if "is not used" in str(w.message)]
    assert len(messages) == 2  # the coarse and the fine stage, each started afresh
    for message in messages:
        assert "it was made with other solver options (" in message and "afresh" in message
        assert "solver.temperature_end 0.25 -> 1.0" in message and "solver.priors.tv.weight 'auto' -> 0.05" in message
    torch.testing.assert_close(rerun.occupancy, clean.occupancy, atol=1e-6, rtol=0)
    again = VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **changed).solve(meas, op)  # same options
    torch.testing.assert_close(again.occupancy, clean.occupancy, atol=0, rtol=0)


def test_a_checkpoint_is_resumed_when_only_the_surface_refit_changed(tmp_path):
    """The refit runs on the optimisation's result, as the threshold is set on it: turning it on for a checkpointed
    solve resumes the solve (before: every stage was ignored as made with other solver options and began afresh)."""
    truth, op, meas = noise_free_problem(3, None)
    options = {"iterations": 20, "tol": 0.0, "progress": False, "coarse_to_fine": False}
    plain = VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), **options).solve(meas, op)
    refit = {"steps": 2, "probe_steps": 2, "holdout_every": 2, "min_gain": 0.0, "still_falling": 0.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no checkpoint is ignored
        resumed = VoxelSolver(checkpoint=Checkpoint(tmp_path, every=10), surface_refit=refit, **options).solve(meas, op)
    torch.testing.assert_close(resumed.occupancy, plain.occupancy, atol=0, rtol=0)
    assert resumed.history["loss"] == plain.history["loss"] and resumed.info["surface_refit"]["reason"]

def test_memory_estimate_of_the_paper_size_voxel_run_is_above_the_measured_peak_and_below_the_target():
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["resolution=240", "n_dips=5760", "solver=voxel"])
    total = estimate_memory(cfg).total
    assert 2.03e9 < total < 8e9  # measured peak RSS of the 240^3 / 5,760-dip voxel solve: 2.03 GB; target 8 GB
