"""Tune prior weights by minimising the Chamfer distance of the jobs (Optuna >= 3; the `sweeps` extra).

    python scripts/tune.py                                    # 20 trials: voxel solver, 32^3, 51 dips
    python scripts/tune.py --trials 50 solver=implicit        # any job option as a Hydra override
    python scripts/tune.py --param solver.priors.tv.weight=1e-4:1 --param solver.lr=0.01:0.3
    python scripts/tune.py --storage sqlite:///optuna.db      # resume or share a study
    python scripts/compare.py tune/dipnet_prior_weights       # tabulate the trials

Trial ``i`` runs in ``<out>/<i>``; the best values go to ``<out>/best.yaml`` with the best trial's consistency
verdict: a trial whose result is ``inconsistent`` with its dips ranks behind every consistent one, and a best
trial that is inconsistent is named with a warning (:mod:`dipnet.jobs.tuning`), and so is a best value at an end of
its range (the optimum may lie beyond it). An ``--out`` that already holds a study is refused (exit 2) unless
``--storage`` continues that study.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from dipnet.jobs.cli import user_errors
from dipnet.core.console import report
from dipnet.jobs.tuning import DEFAULT_PARAMS, NoBestTrialError, Param, best_trial, check_study, range_edges, tune


def parse_param(text: str) -> Param:
    """:meth:`Param.parse` for argparse: its reason in the error (argparse shows a ``ValueError`` as "invalid parse
    value" alone)."""
    try:
        return Param.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of every job, e.g. solver=implicit n_dips=80")
    parser.add_argument("--trials", type=int, default=20, help="number of trials")
    parser.add_argument("--param", action="append", type=parse_param, metavar="KEY=LOW:HIGH[:log|linear]",
                        help="a tuned option (repeat; default: the tv and binary prior weights in [1e-4, 1], log)")
    parser.add_argument("--out", type=Path, help="study directory (default: tune/<study name>)")
    parser.add_argument("--study-name", default="dipnet_prior_weights")
    parser.add_argument("--storage", help="Optuna storage URL, e.g. sqlite:///optuna.db (default: in memory)")
    parser.add_argument("--seed", type=int, default=0, help="sampler seed")
    parser.add_argument("--startup-trials", type=int, default=8, help="random trials before TPE")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    params = args.param or DEFAULT_PARAMS
    with user_errors():  # a bad option: one line (before logging repeats it) and exit 2, before any trial
        check_study(args.trials, params, args.overrides)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = args.out or Path("tune") / args.study_name
    try:
        with user_errors():  # a folder holding another study: one line, before any trial
            study = tune(out, args.trials, params, args.overrides, seed=args.seed,
                         n_startup_trials=args.startup_trials, storage=args.storage, study_name=args.study_name)
    except NoBestTrialError as exc:  # the trials ran, but none has a result worth recommending
        report(f"error: {exc}")
        return 1
    best = best_trial(study, out)
    verdict = best.user_attrs.get("consistency") or "no consistency verdict"
    edges = range_edges(best.params, params)
    at_edge = "".join(f"; {key} at the {end} end of its range" for key, end in edges.items())
    print(f"best chamfer {best.value:.5f} (trial {best.number}, {verdict}): {best.params}{at_edge}; "
          f"written to {out / 'best.yaml'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
