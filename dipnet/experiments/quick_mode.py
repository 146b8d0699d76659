"""The benchmarks' ``--quick`` mode: its settings fill only the options the command line leaves out.

Every ``scripts/bench_*.py`` has a ``--quick`` mode that sets a smaller problem (a grid size, meshes, budgets).
An option given on the command line beside ``--quick`` keeps its value: ``--quick --n 48`` runs the quick
problem at 48^3, where the quick settings used to replace it without a word (a table and ``RESULT`` line of
another problem than the one asked for).
"""

from __future__ import annotations

import argparse
import copy
from collections.abc import Sequence


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> set[str]:
    """The destinations (``args`` attribute names) of the options that ``argv`` (``None``: ``sys.argv[1:]``)
    gives explicitly, whatever their values (``--n 64`` counts when 64 is the default too)."""
    probe = copy.deepcopy(parser)
    for action in probe._actions:  # argparse keeps its actions here; no public accessor exists
        action.default = argparse.SUPPRESS
        action.required = False
    return set(vars(probe.parse_args(argv)))


def apply_quick(args: argparse.Namespace, given: set[str], **settings: object) -> argparse.Namespace:
    """Set each of ``settings`` (option destination -> the quick mode's value) on ``args`` unless ``given``
    (:func:`given_options`) holds it; returns ``args``."""
    for name, value in settings.items():
        if name not in given:
            setattr(args, name, value)
    return args
