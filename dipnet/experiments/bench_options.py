"""The benchmarks' run options shared by ``scripts/bench_quality.py``, ``scripts/bench_uncertainty.py`` and
``scripts/bench_planning.py``, checked before any case runs.

A bad value of one of these used to surface late: ``--threads -1`` as a traceback, ``--threads 0`` not at all
(torch's default taken unsaid), ``--seed -1`` at the first simulation, ``--snr nan`` at the first noisy case (after
the noise-free ones), ``--json`` into a missing folder only after every case had run and ``--generated -2`` not at all.
"""

from __future__ import annotations

import argparse

from dipnet.simulator.physics import check_snr_db


def check_run_options(args: argparse.Namespace) -> None:
    """Refuse the shared run options of ``args`` that no case could use.

    Reads ``args.noise`` and ``args.snr`` (dB; checked only when ``"snr"`` or ``"unstated"`` noise is asked for;
    a benchmark without ``--noise`` is always noisy at ``--snr``), ``args.seed`` (``>= 0``), ``args.threads``
    (``None`` or ``>= 1``), ``args.json`` (``None`` or a file in an existing folder) and ``args.generated`` (the
    number of generated test shapes, ``>= 0``; a benchmark without it generates none) with ``args.generated_first``
    (their first seed, ``>= 0``: was numpy's ``expected non-negative integer`` after the mesh cases, naming no option).

    Raises:
        ValueError: naming the first bad option and its value.
    """
    if {"snr", "unstated"} & set(getattr(args, "noise", ("snr",))):
        try:
            check_snr_db(args.snr)
        except ValueError as exc:
            raise ValueError(f"--snr: {exc}") from None
    if args.seed < 0:
        raise ValueError(f"--seed must be 0 or more, got {args.seed}")
    if args.threads is not None and args.threads < 1:
        raise ValueError(f"--threads must be 1 or more, got {args.threads}")
    if args.json is not None and not args.json.parent.is_dir():
        raise ValueError(f"--json {args.json}: no folder {args.json.parent}")
    if getattr(args, "generated", 0) < 0:
        raise ValueError(f"--generated must be 0 or more, got {args.generated}")
    if getattr(args, "generated", 0) and getattr(args, "generated_first", 0) < 0:  # numpy's seeds are >= 0
        raise ValueError(f"--generated-first must be 0 or more (the seed of the first generated shape), "
                         f"got {args.generated_first}")


def thread_count(text: str) -> int:
    """The ``argparse`` type of a benchmark's ``--threads``: a whole number >= 1 (``--threads 0`` was torch's
    ``RuntimeError: set_num_threads expects a positive integer`` traceback, exit 1)."""
    try:
        threads = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number of torch threads, 1 or more, got {text!r}") from None
    if threads < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more (torch threads), got {threads}")
    return threads
