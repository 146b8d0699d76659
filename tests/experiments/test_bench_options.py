"""The benchmarks' shared run options are checked before any case runs."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from dipnet.experiments.bench_options import check_run_options


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
])
def test_each_bad_run_option_is_named(tmp_path, given, message):
    with pytest.raises(ValueError, match=message):
        check_run_options(_args(tmp_path, **given))
