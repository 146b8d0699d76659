"""The benchmarks' run options, checked before any case runs: :func:`check_run_options` (``--snr``, ``--seed``,
``--threads``, ``--json``, ``--generated``, ``--fill``) and the ``argparse`` types :func:`count_type` (a count of at
least some minimum), :func:`number_type` (a finite number, e.g. positive) and :func:`grid_size_type` (voxels per
axis), shared by every ``scripts/bench_*.py``.

A bad value of one of these used to surface late: ``--threads -1`` as a traceback, ``--threads 0`` not at all
(torch's default taken unsaid), ``--seed -1`` at the first simulation, ``--snr nan`` at the first noisy case (after
the noise-free ones), ``--json`` into a missing folder only after every case had run and ``--generated -2`` not at all.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from dipnet.core.counts import is_real
from dipnet.core.grid import Grid
from dipnet.simulator.physics import check_snr_db


def check_run_options(args: argparse.Namespace) -> None:
    """Refuse the shared run options of ``args`` that no case could use.

    Reads ``args.noise`` and ``args.snr`` (dB; checked only when ``"snr"`` or ``"unstated"`` noise is asked for;
    a benchmark without ``--noise`` is always noisy at ``--snr``), ``args.seed`` (``>= 0``), ``args.threads``
    (``None`` or ``>= 1``), ``args.json`` (``None`` or a file in an existing folder), ``args.generated`` (the
    number of generated test shapes, ``>= 0``; a benchmark without it generates none) with ``args.generated_first``
    (their first seed, ``>= 0``: was numpy's ``expected non-negative integer`` after the mesh cases, naming no option)
    and ``args.fill`` (the mesh's radius over the working ball's, in (0, 1]). A benchmark without ``--threads``,
    ``--json`` or ``--fill`` is not asked for them.

    Raises:
        ValueError: naming the first bad option and its value.
    """
    if hasattr(args, "snr") and {"snr", "unstated"} & set(getattr(args, "noise", ("snr",))):
        try:
            check_snr_db(args.snr)
        except ValueError as exc:
            raise ValueError(f"--snr: {exc}") from None
    if getattr(args, "seed", 0) < 0:
        raise ValueError(f"--seed must be 0 or more, got {args.seed}")
    if getattr(args, "threads", None) is not None and args.threads < 1:
        raise ValueError(f"--threads must be 1 or more, got {args.threads}")
    if getattr(args, "json", None) is not None and not args.json.parent.is_dir():
        raise ValueError(f"--json {args.json}: no folder {args.json.parent}")
    if getattr(args, "generated", 0) < 0:
        raise ValueError(f"--generated must be 0 or more, got {args.generated}")
    if getattr(args, "generated", 0) and getattr(args, "generated_first", 0) < 0:  # numpy's seeds are >= 0
        raise ValueError(f"--generated-first must be 0 or more (the seed of the first generated shape), "
                         f"got {args.generated_first}")
    if hasattr(args, "fill") and not (is_real(args.fill) and 0 < args.fill <= 1):
        raise ValueError(f"--fill must be in (0, 1] (the mesh's radius over the working ball's: above 1 the mesh "
                         f"reaches beyond the working ball, which the grid cannot hold), got {args.fill:g}")


def count_type(minimum: int, what: str) -> Callable[[str], int]:
    """The ``argparse`` type of a count of ``what`` of ``minimum`` or more (e.g. ``count_type(1, "random rigs")``):
    argparse refuses anything else in one line naming the option, exit 2, before any work (``--rigs 0`` was a
    ``StatisticsError`` traceback after the run, ``--trials 0`` a run of nothing, exit 0)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number of {what}, {minimum} or more, got {text!r}") \
                from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be {minimum} or more ({what}), got {value}")
        return value
    parse.__name__ = f"whole number of {what}"
    return parse


def number_type(what: str, *, above: float | None = None, at_least: float | None = None,
                no_limit: bool = False) -> Callable[[str], float]:
    """The ``argparse`` type of a finite number of ``what`` (with its unit), ``above`` or ``at_least`` a bound when
    given (e.g. ``number_type("seconds", above=0)``): argparse refuses ``nan``, ``inf`` (unless ``no_limit``: a
    limit's ``inf`` is none) and a value out of range in one line naming the option, exit 2, before any work."""
    bound = f" above {above:g}" if above is not None else f", {at_least:g} or more" if at_least is not None else ""
    bound += " (inf: no limit)" if no_limit else ""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) or (no_limit and value == math.inf)) or (above is not None and value <= above) or \
                (at_least is not None and value < at_least):
            raise argparse.ArgumentTypeError(f"must be a finite number of {what}{bound}, got {text!r}")
        return value
    parse.__name__ = f"number of {what}"
    return parse


def grid_size_type(ndim: int = 3, *, zero: str | None = None) -> Callable[[str], int]:
    """The ``argparse`` type of a grid's voxels per axis N, as :class:`~dipnet.core.grid.Grid` takes it in ``ndim``
    dimensions; ``zero``: what 0 means where it is allowed (e.g. ``"skip"``). Anything else is refused in one line
    naming the option, exit 2, before any case."""
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number of voxels per axis, got {text!r}") from None
        if n == 0 and zero is not None:
            return n
        try:
            Grid(n, ndim)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc) + (f" (or 0: {zero})" if zero is not None else "")) from None
        return n
    parse.__name__ = "grid size"
    return parse


#: The ``argparse`` type of a benchmark's ``--threads``: a whole number >= 1 (``--threads 0`` was torch's
#: ``RuntimeError: set_num_threads expects a positive integer`` traceback, exit 1).
thread_count = count_type(1, "torch threads")


def refuse_bad_run_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """:func:`check_run_options` for a benchmark's ``parse_args``: the first bad option as ``parser.error`` (one line
    naming it, exit 2)."""
    try:
        check_run_options(args)
    except ValueError as exc:
        parser.error(str(exc))
