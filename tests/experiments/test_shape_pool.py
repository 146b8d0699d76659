"""The benchmarks' shape pool: every built-in and bundled mesh by name, each made at the radius asked for."""

import pytest

from dipnet.experiments.shape_pool import shape_makers, shape_names
from dipnet.preprocessing.datasets import mesh_names


def test_the_pool_holds_the_built_ins_and_every_bundled_mesh_in_order():
    names = shape_names()
    assert names[:7] == ["disk_2d", "chamber_box_2d", "elephant_2d", "ball_3d", "box_3d", "torus_3d", "chamber_box_3d"]
    assert names[7:] == mesh_names()
    assert shape_names(ndim=2) == names[:3] and shape_names(ndim=3) == names[3:]


@pytest.mark.parametrize("name, ndim", [("ball_3d", 3), ("elephant_2d", 2), ("bunny", 3)])
def test_a_shape_is_made_at_the_radius_asked_for(name, ndim):
    made_ndim, make = shape_makers()[name]
    shape = make(30.0)
    assert made_ndim == shape.ndim == ndim and shape.radius() == pytest.approx(30.0, rel=1e-6)


def test_an_unknown_name_or_one_of_another_dimension_is_named_with_the_known_ones():
    with pytest.raises(ValueError, match="no shape named teapot .*known: disk_2d"):
        shape_names(["teapot", "ball_3d"])
    with pytest.raises(ValueError, match="no shape named disk_2d"):
        shape_names(["disk_2d"], ndim=3)
    assert shape_names(["bunny", "ball_3d"]) == ["ball_3d", "bunny"]


def test_the_pool_options_parse_with_their_defaults():
    import argparse

    from dipnet.experiments.shape_pool import add_pool_options

    parser = argparse.ArgumentParser()
    add_pool_options(parser, trials=3, resolution=24, shapes_help="shapes")
    args = parser.parse_args(["--shapes", "bunny", "ball_3d", "--json", "rows.json"])
    assert (args.trials, args.resolution, args.seed, args.threads) == (3, 24, 2026, 2)
    assert args.shapes == ["bunny", "ball_3d"] and str(args.json) == "rows.json"


def test_a_pool_run_sets_its_threads_quiets_the_log_and_seeds_its_cases():
    import argparse
    import logging

    import torch

    from dipnet.experiments.shape_pool import start_pool_run

    log, level, threads = logging.getLogger("dipnet"), logging.getLogger("dipnet").level, torch.get_num_threads()
    try:
        args = argparse.Namespace(threads=1, seed=7)
        draws = [start_pool_run(args).integers(1 << 30, size=3).tolist() for _ in range(2)]
        assert draws[0] == draws[1] and torch.get_num_threads() == 1 and log.level == logging.ERROR
    finally:
        log.setLevel(level)
        torch.set_num_threads(threads)
