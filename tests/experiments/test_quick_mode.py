"""The benchmarks' --quick settings fill only the options the command line leaves out."""

from __future__ import annotations

import argparse

import pytest

from dipnet.experiments.quick_mode import apply_quick, given_options
from tests.script_modules import load_script


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    p.add_argument("--n", type=int, default=64)
    p.add_argument("--meshes", nargs="*")
    p.add_argument("--noise", nargs="+", default=["clean", "snr"])
    p.add_argument("--quick", action="store_true")
    return p


def test_given_options_are_those_on_the_command_line_whatever_their_values():
    p = _parser()
    assert given_options(p, ["--quick"]) == {"quick"}
    assert given_options(p, ["--quick", "--n", "64", "--meshes", "torus"]) == {"quick", "n", "meshes"}
    assert p.parse_args([]).n == 64  # the parser itself keeps its defaults


def test_quick_settings_fill_only_the_options_left_out():
    p = _parser()
    argv = ["--quick", "--n", "48"]
    args = apply_quick(p.parse_args(argv), given_options(p, argv), n=32, noise=["clean"], meshes=["bunny"])
    assert (args.n, args.noise, args.meshes) == (48, ["clean"], ["bunny"])


@pytest.mark.parametrize("name, argv, expected", [
    ("bench_quality", ["--quick", "--n", "24"], {"n": 24, "budgets": [41, 123], "noise": ["clean"]}),
    ("bench_quality", ["--quick"], {"n": 32, "budgets": [41, 123], "meshes": ["bunny", "torus"]}),
    ("bench_quality", ["--headline", "--quick", "--generated", "0", "--noise", "clean", "snr"],
     {"n": 64, "generated": 0, "noise": ["clean", "snr"], "workers": 2}),
    ("bench_uncertainty", ["--quick", "--noise", "snr"], {"n": 24, "noise": ["snr"], "meshes": ["bunny", "torus"]}),
    ("bench_calibration", ["--quick", "--rigs", "5"], {"rigs": 5, "n": 32, "iterations": 80}),
    ("bench_reference_plans", ["--quick", "--seed", "3"], {"rigs": 5, "seed": 3}),
    ("bench_reference_plans", ["--quick", "--rigs", "8", "--plans", "grid16_35"], {"rigs": 8, "plans": ["grid16_35"]}),
    ("bench_scale", ["--quick", "--meshes", "torus"], {"n": [128], "meshes": ["torus"], "fractions": [0.03]}),
    ("bench_symmetry_check", ["--quick", "--seed", "3"], {"trials": 2, "seed": 3}),
    ("bench_symmetry_check", ["--quick", "--trials", "4"], {"trials": 4}),
    ("bench_dip_agreement", ["--quick", "--seed", "3"], {"trials": 1, "seed": 3}),
    ("bench_dip_agreement", ["--quick", "--shapes", "bunny"], {"trials": 1, "shapes": ["bunny"]}),
    ("bench_consistency", ["--quick", "--seed", "3"], {"trials": 2, "seed": 3}),
    ("bench_consistency", ["--quick", "--trials", "3", "--shapes", "bunny"], {"trials": 3, "shapes": ["bunny"]}),
])
def test_a_benchmark_run_with_quick_keeps_the_options_given_beside_it(name, argv, expected):
    """``--quick --n 24`` used to run at the quick mode's 32^3 and print its table and RESULT line as asked."""
    args = load_script(name).parse_args(argv)
    assert {key: getattr(args, key) for key in expected} == expected
