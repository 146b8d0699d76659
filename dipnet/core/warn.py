"""A problem reported twice on purpose: :func:`warn` logs it and issues it as a Python warning.

The log line reaches a run's log file (Hydra's ``<job>.log``, a scan's journal); the warning reaches Python
callers (``pytest.warns``, ``warnings.catch_warnings``, ``-W error``). Under a script
:func:`dipnet.jobs.warnings_once.log_warnings_once` shows such a text once on the console.
"""

from __future__ import annotations

import logging
import warnings


def log_and_warn(log: logging.Logger, message: str, category: type[Warning] = UserWarning, stacklevel: int = 2) -> None:
    """Log ``message`` at WARNING on ``log`` and issue it as a ``category`` warning.

    Args:
        log: the reporting module's logger.
        message: the text, whole (it is not %-formatted).
        category: the warning's class.
        stacklevel: as for :func:`warnings.warn` called in the caller's place (2: the caller's caller's line).
    """
    log.warning("%s", message)
    warnings.warn(message, category, stacklevel=stacklevel + 1)
