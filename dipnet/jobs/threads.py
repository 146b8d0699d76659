"""How many CPU threads a job uses: one place for torch's (and so the NUFFT's) thread count.

torch's default is every core of the machine, whatever else runs: on a shared 2-core machine
two jobs with 2 threads each ran 5-17x slower than with one. The default here is one thread
per job in a sweep (Hydra multirun: jobs run side by side) and otherwise ``OMP_NUM_THREADS``
when set, else the cores this process may use (``len(os.sched_getaffinity(0))``, which honours
``taskset`` and cgroup CPU sets). ``threads=N`` in the config overrides both.
"""

from __future__ import annotations

import logging
import os

import torch

log = logging.getLogger(__name__)


def available_cores() -> int:
    """CPU cores this process may run on (its affinity set; ``os.cpu_count()`` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def in_multirun() -> bool:
    """True inside a Hydra multirun (sweep) job."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def default_threads(multirun: bool) -> int:
    """1 in a sweep; else ``OMP_NUM_THREADS`` when set (the user's explicit choice), else the
    available cores."""
    if multirun:
        return 1
    env = os.environ.get("OMP_NUM_THREADS", "")
    return int(env) if env.isdigit() and int(env) > 0 else available_cores()


def configure_threads(threads: int | None = None, multirun: bool | None = None) -> int:
    """Set torch's intra-op thread count to ``threads`` (``None``: :func:`default_threads`) and
    return it. Raises ``ValueError`` for a count below 1."""
    if threads is None:
        threads = default_threads(in_multirun() if multirun is None else multirun)
    if not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be a positive integer or null, got {threads!r}")
    torch.set_num_threads(threads)
    log.info("torch threads: %d", threads)
    return threads
