"""One line on the terminal for an entry point's end: :func:`report` and :func:`interrupted`.

Used by every room's entry points (``dipnet.jobs.cli``'s error contract, ``scripts/scan.py``, the monitor),
so it sits in the core: it needs nothing but the standard library.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Callable, Iterator

log = logging.getLogger("dipnet")


@contextlib.contextmanager
def interrupted(hint: Callable[[], str], exit_code: int = 130) -> Iterator[None]:
    """Turn Ctrl-C (``KeyboardInterrupt``) into one line ``interrupted: <hint()>`` and exit
    ``exit_code`` (130, the shell's code for SIGINT); ``hint`` says how to resume."""
    try:
        yield
    except KeyboardInterrupt:
        report(f"interrupted: {hint()}")
        raise SystemExit(exit_code) from None


def report(message: str) -> None:
    """Print ``message`` once on stderr and log it as an error everywhere but the terminal: the log file
    (Hydra's ``<job>.log``) and a scan's monitor journal keep it.

    The console handlers (a ``StreamHandler`` that is not a ``FileHandler``: Hydra's on stdout,
    ``logging.basicConfig``'s on stderr) are left out: they would show the line a second time.
    """
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None)
    logger: logging.Logger | None = log
    while logger is not None:
        for handler in logger.handlers:
            console = isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler)
            if not console and record.levelno >= handler.level:
                handler.handle(record)
        logger = logger.parent if logger.propagate else None
    print(message, file=sys.stderr)
