"""The benchmarks' shared run options are checked before any case runs."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from dipnet.experiments.bench_options import check_run_options, count_type, grid_size_type, number_type


def _args(tmp_path: Path, **given) -> argparse.Namespace:
    values = dict(noise=["clean", "snr"], snr=30.0, seed=0, threads=None, json=tmp_path / "rows.json", generated=0)
    return argparse.Namespace(**{**values, **given})


def test_usable_run_options_pass(tmp_path):
    check_run_options(_args(tmp_path))
    check_run_options(_args(tmp_path, threads=1, seed=7, json=None))
    check_run_options(_args(tmp_path, noise=["clean"], snr=float("nan")))  # no noisy case reads --snr


@pytest.mark.parametrize("given, message", [
    ({"snr": float("nan")}, r"--snr: snr_db must be a number of dB in \[-20, 200\]"),
    ({"noise": ["unstated"], "snr": 500.0}, r"--snr: snr_db must be"),
    ({"seed": -1}, r"--seed must be 0 or more, got -1"),
    ({"threads": 0}, r"--threads must be 1 or more, got 0"),
    ({"threads": -2}, r"--threads must be 1 or more, got -2"),
    ({"json": Path("/nonexistent/dir/rows.json")}, r"--json /nonexistent/dir/rows.json: no folder /nonexistent/dir"),
    ({"generated": -2}, r"--generated must be 0 or more, got -2"),
    ({"generated": 1, "generated_first": -1}, r"--generated-first must be 0 or more \(the seed of the first"),
    ({"fill": 2.0}, r"--fill must be in \(0, 1\] \(the mesh's radius over the working ball's: above 1"),
    ({"fill": 0.0}, r"--fill must be in \(0, 1\]"),
    ({"fill": float("nan")}, r"--fill must be in \(0, 1\]"),
])
def test_each_bad_run_option_is_named(tmp_path, given, message):
    with pytest.raises(ValueError, match=message):
        check_run_options(_args(tmp_path, **given))


def test_a_benchmark_without_an_option_is_not_asked_for_it():
    """bench_symmetry_check has only --seed, bench_reference_plans no --json or --fill: their absence is no error."""
    check_run_options(argparse.Namespace(seed=3))
    check_run_options(argparse.Namespace(seed=0, snr=30.0, threads=2))
    with pytest.raises(ValueError, match=r"--seed must be 0 or more, got -1"):
        check_run_options(argparse.Namespace(seed=-1))


def _parser(**types) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    for name, kind in types.items():
        parser.add_argument(f"--{name}", type=kind)
    return parser


def test_a_count_type_takes_whole_numbers_from_its_minimum():
    parser = _parser(rigs=count_type(1, "random rigs"), seed=count_type(0, "seed"))
    assert vars(parser.parse_args(["--rigs", "1", "--seed", "0"])) == {"rigs": 1, "seed": 0}


@pytest.mark.parametrize("argv, message", [
    (["--rigs", "0"], r"argument --rigs: must be 1 or more \(random rigs\), got 0"),
    (["--rigs", "-3"], r"argument --rigs: must be 1 or more \(random rigs\), got -3"),
    (["--rigs", "2.5"], r"argument --rigs: must be a whole number of random rigs, 1 or more, got '2.5'"),
    (["--rigs", "many"], r"argument --rigs: must be a whole number of random rigs, 1 or more, got 'many'"),
    (["--offset", "nan"], r"argument --offset: must be a finite number of mm, 0 or more, got 'nan'"),
    (["--offset", "-1"], r"argument --offset: must be a finite number of mm, 0 or more, got '-1'"),
    (["--step", "0"], r"argument --step: must be a finite number of mm above 0, got '0'"),
    (["--step", "inf"], r"argument --step: must be a finite number of mm above 0, got 'inf'"),
    (["--step", "two"], r"argument --step: must be a finite number of mm above 0, got 'two'"),
])
def test_a_bad_count_or_number_is_refused_naming_the_option(capsys, argv, message):
    """The shared argparse types of the benchmarks' counts and numbers: one line naming the option, exit 2, before
    any work (``--rigs 0`` was a ``StatisticsError`` traceback after the run, ``--trials 0`` a run of nothing)."""
    parser = _parser(rigs=count_type(1, "random rigs"), offset=number_type("mm", at_least=0),
                     step=number_type("mm", above=0))
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and re.search(f"error: {message}", err), err


def test_a_number_type_takes_finite_numbers_in_range():
    parser = _parser(offset=number_type("mm", at_least=0), step=number_type("mm", above=0), any=number_type("mm"))
    assert vars(parser.parse_args(["--offset", "0", "--step", "1e-3", "--any", "-5"])) == \
        {"offset": 0.0, "step": 1e-3, "any": -5.0}


def test_a_limit_may_be_no_limit():
    parser = _parser(limit=number_type("seconds", above=0, no_limit=True))
    assert parser.parse_args(["--limit", "inf"]).limit == float("inf")
    with pytest.raises(SystemExit):
        parser.parse_args(["--limit", "nan"])


def test_a_grid_size_type_takes_what_a_grid_takes_and_zero_only_where_it_means_something(capsys):
    parser = _parser(n=grid_size_type(3), radon=grid_size_type(2, zero="skip"))
    assert vars(parser.parse_args(["--n", "4", "--radon", "0"])) == {"n": 4, "radon": 0}
    for argv, message in [(["--n", "0"], r"argument --n: grid resolution n must be an integer >= 4, got 0$"),
                          (["--n", "3.5"], r"argument --n: must be a whole number of voxels per axis, got '3.5'"),
                          (["--radon", "-5"], r"argument --radon: grid resolution n must be an integer >= 4, got -5 "
                                              r"\(or 0: skip\)")]:
        with pytest.raises(SystemExit) as exit_:
            parser.parse_args(argv)
        err = capsys.readouterr().err.strip()
        assert exit_.value.code == 2 and re.search(f"error: {message}", err), err
