"""The scan side of the monitor: what the raw scan does not record, in a journal beside it.

The raw scan holds the readings; a monitor also shows the rig's state, the warnings and the
safe-stop message. :class:`MonitorJournal` writes them to ``<scan>.monitor.jsonl``
(:func:`~dipnet.monitor.tail.journal_path`), one JSON object per line:

    {"type": "warning", "time": 1732410000.1, "logger": "dipnet.rig.grbl", "message": "..."}
    {"type": "status", "time": ..., "where": "orientation 3 (tilt 45, spin 90), reading 12 at 24 mm",
     "report": "<Idle|MPos:0.000,0.000,-24.000,45.000,90.000|FS:0,0>"}
    {"type": "stopped", "time": ..., "message": "scan stopped at ...: ...; object lifted: ..."}

It never talks to the rig: warnings come from the ``dipnet`` logger (a logging handler), the
status from a daemon thread that samples, twice a second, the runner's ``where`` and the last
status report the controller already parsed (``controller.last_status``); nothing waits on it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from dipnet.core.strict_json import dumps
from dipnet.monitor.tail import journal_path

#: Seconds between two status samples.
STATUS_PERIOD_S = 0.5


class MonitorJournal(logging.Handler):
    """Append-only journal of one scan (use as a context manager around the scan).

    Args:
        scan_path: the raw scan file; the journal is ``<scan>.monitor.jsonl`` beside it.
        logger: the logger whose warnings and errors are journalled (default ``dipnet``).
    """

    def __init__(self, scan_path: str | Path, logger: str = "dipnet") -> None:
        super().__init__(level=logging.WARNING)
        self.path = journal_path(scan_path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_BINARY", 0), 0o644)
        self._logger = logging.getLogger(logger)
        self._runner: Any = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample_loop, name="monitor-journal", daemon=True)
        self._last_status: tuple[str, str] | None = None

    def __enter__(self) -> "MonitorJournal":
        self._logger.addHandler(self)
        self.write({"type": "session", "pid": os.getpid()})
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2 * STATUS_PERIOD_S)
        self._sample()
        self._logger.removeHandler(self)
        self.close()

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        super().close()

    def watch(self, runner: Any) -> None:
        """Sample ``runner`` (a :class:`~dipnet.rig.runner.ScanRunner`) from now on."""
        self._runner = runner

    def stopped(self, message: str) -> None:
        """Record the safe-stop message (:class:`~dipnet.rig.runner.ScanAborted`)."""
        self.write({"type": "stopped", "message": message})

    def write(self, record: dict[str, Any]) -> None:
        """Append one record (with the time) as one line."""
        if self._fd is None:
            return
        line = dumps({**record, "time": time.time()}, default=str) + "\n"
        os.write(self._fd, line.encode("utf-8"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            kind = "warning" if record.levelno < logging.ERROR else "error"
            self.write({"type": kind, "logger": record.name, "message": record.getMessage()})
        except Exception:  # noqa: BLE001 - a journal must never break the scan
            self.handleError(record)

    def _sample_loop(self) -> None:
        while not self._stop.wait(STATUS_PERIOD_S):
            self._sample()

    def _sample(self) -> None:
        runner = self._runner
        if runner is None:
            return
        report = getattr(runner.controller, "last_status", None)
        status = (str(getattr(runner, "where", "")), format_report(report))
        if status != self._last_status:
            self._last_status = status
            self.write({"type": "status", "where": status[0], "report": status[1],
                        "state": getattr(report, "state", None),
                        "dialect": getattr(runner.controller, "dialect", None)})


def format_report(report: Any) -> str:
    """A parsed status report as the controller sent it (GRBL: ``<Idle|MPos:...|FS:0,0>``); ``""`` for none."""
    if report is None:
        return ""
    if not hasattr(report, "state"):
        return str(report)
    head = report.state if report.substate is None else f"{report.state}:{report.substate}"
    return "<" + "|".join([head, *(f"{key}:{value}" for key, value in report.fields.items())]) + ">"
