"""The benchmarks' job-composed solvers and the generated test seeds they may use."""

import pytest

from dipnet.jobs.configured import check_test_seeds, configured
from dipnet.solvers.voxel import VoxelSolver


def test_a_configured_solver_is_the_jobs_recipe_with_its_seed_in_the_nested_start():
    make = configured("voxel_learned")
    solver = make(seed=7)
    assert make.config_name == "voxel_learned" and isinstance(solver, VoxelSolver)
    assert solver.rounds == 6 and solver.surface_refit is not None and solver.surface_refit.white_share == 0.001
    assert solver.seed == 7 and isinstance(solver.warm_start, VoxelSolver) and solver.warm_start.seed == 7
    assert make(iterations=3).iterations == 3 and make().iterations == 150  # options merged into a fresh copy


def test_generated_test_seeds_must_not_overlap_the_training_seeds():
    check_test_seeds(0, 50)
    with pytest.raises(ValueError, match="overlap"):
        check_test_seeds(990, 20)
    with pytest.raises(ValueError, match="overlap"):
        check_test_seeds(2000, 1)  # a validation seed
