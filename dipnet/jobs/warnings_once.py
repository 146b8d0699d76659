"""Each warning of a command-line job shown once, through logging.

dipnet's modules report a problem twice on purpose (:func:`dipnet.core.warn.log_and_warn`): ``log.warning``
for the run's log and ``warnings.warn`` for Python callers (``pytest.warns``, ``-W error``). Under a
script both reached the console: the log record through Hydra's log handlers, the warning
through Python's default ``warnings.showwarning`` (a second, differently formatted line on
stderr, with the source line of the caller). :func:`log_warnings_once` replaces
``showwarning`` for the script's process: a warning whose text a logger has already emitted at
WARNING or above is not shown again, any other is logged once by the ``py.warnings`` logger
(so it also reaches the run's log file). Python's warning filters still apply first, so
``-W error`` and ``warnings.catch_warnings`` behave as before.
"""

from __future__ import annotations

import logging
import warnings
from typing import Any

#: The logger of warnings that no dipnet logger reported (Python's own name for it).
WARNINGS_LOGGER = "py.warnings"

_logged: set[str] = set()
_installed = False


def _record_factory(base: Any) -> Any:
    """A log-record factory that remembers the text of every WARNING-or-above record."""
    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = base(*args, **kwargs)
        if record.levelno >= logging.WARNING:
            _logged.add(record.getMessage())
        return record
    return factory


def _show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
          file: Any = None, line: str | None = None) -> None:
    """``warnings.showwarning`` replacement: log ``message`` unless a logger already said it."""
    text = str(message)
    if text in _logged:
        return
    logging.getLogger(WARNINGS_LOGGER).warning("%s: %s", category.__name__, text)


def log_warnings_once() -> None:
    """Route this process's warnings through logging, each text once (idempotent)."""
    global _installed
    if _installed:
        return
    logging.setLogRecordFactory(_record_factory(logging.getLogRecordFactory()))
    warnings.showwarning = _show
    _installed = True
