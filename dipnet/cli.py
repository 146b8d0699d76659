"""Helpers for the command-line entry points."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator

from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

log = logging.getLogger("dipnet")

#: Exceptions that mean "the user's input is wrong", reported in one line, not a traceback.
#: Set DIPNET_DEBUG=1 to get the full traceback instead.
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, KeyError, HydraException,
                                                OmegaConfBaseException)


@contextlib.contextmanager
def user_errors(exit_code: int = 2) -> Iterator[None]:
    """Turn bad-input exceptions into a one-line ``error: ...`` message and exit ``exit_code``."""
    try:
        yield
    except USER_ERRORS as exc:
        if os.environ.get("DIPNET_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or type(exc).__name__
        log.error("error: %s", message)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(exit_code) from None
