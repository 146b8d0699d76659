"""Solvers of the benchmarks as a job composes them, and the generated test seeds they may use.

:func:`configured` builds a solver from ``conf/solver/<name>.yaml`` the way ``solver=<name>`` does in a
job (``scripts/bench_quality.py`` and ``scripts/bench_uncertainty.py`` run the learned prior,
``solver=voxel_learned``, through it, not through a second recipe written in a script);
:func:`check_test_seeds` refuses generated shapes the learned prior's weights were trained or validated on.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

from hydra.utils import instantiate
from omegaconf import OmegaConf

from dipnet.jobs.tuning import compose_job
from dipnet.solvers.base import Solver
from dipnet.solvers.denoiser import load_weights


def configured(name: str) -> Callable[..., Solver]:
    """A solver factory for ``conf/solver/<name>.yaml``, the recipe ``solver=<name>`` runs in a job
    (composed once per progress and seed setting, which ``output.progress`` and ``seed`` pass on to a warm start
    too); further keyword options are merged into that config (e.g. ``priors={"learned": {"weight": 3}}``).

    The factory takes ``progress`` (default ``False``), ``seed`` (the job's ``seed``, default 0) and the options."""
    @functools.cache
    def config(progress: bool, seed: int):
        return compose_job([f"solver={name}", f"seed={seed}", f"output.progress={progress}"]).solver

    def make(progress: bool = False, seed: int = 0, **options) -> Solver:
        return instantiate(OmegaConf.merge(config(bool(progress), int(seed)), options))
    make.config_name = name  # type: ignore[attr-defined]  # which conf/solver file it composes
    return make


def check_test_seeds(first: int, count: int) -> None:
    """Refuse generated test seeds ``first`` .. ``first + count - 1`` that the learned prior's shipped weights
    were trained or validated on (their meta's ``train_seeds`` / ``val_seeds`` ranges).

    Raises:
        ValueError: an overlap, naming it.
    """
    config = load_weights(None)[1].get("config", {})
    used = set()
    for key in ("train_seeds", "val_seeds"):
        if key in config:
            used.update(range(*config[key]))
    overlap = used & set(range(first, first + count))
    if overlap:
        raise ValueError(f"generated test seeds {first}..{first + count - 1} overlap the prior's training / "
                         f"validation seeds ({min(overlap)}..{max(overlap)}): choose another --generated-first")
