"""``scripts/scan.py monitor=true``: the monitor beside a scan, in its own process.

:func:`scan_monitor` starts ``python -m dipnet.monitor RUN_DIR --wait`` (:mod:`dipnet.monitor.cli`: the
server and the running reconstruction, niced) as a separate process, so the page's work never runs in
the scan's process, and opens the scan's :class:`~dipnet.monitor.journal.MonitorJournal`. When the
scan ends the monitor process is stopped; ``scripts/monitor.py RUN_DIR`` shows the finished scan.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from dipnet.core.optional import MissingExtraError, optional_import
from dipnet.monitor.journal import MonitorJournal
from dipnet.monitor.server import MonitorError, check_port

log = logging.getLogger(__name__)

#: How much lower the monitor process runs than the scan (its reconstruction worker lower still).
NICE = 10


@contextmanager
def scan_monitor(scan_path: str | Path, port: int = 8765, host: str = "127.0.0.1",
                 options: tuple[str, ...] = ()) -> Iterator[MonitorJournal]:
    """Serve the monitor of the scan written to ``scan_path`` for the ``with`` block; yields the
    journal the scan records its warnings, status and safe-stop message in.

    Raises:
        MonitorError: the port is in use, or fastapi, uvicorn or plotly is missing (the ``monitor``
            extra), before the scan starts.
    """
    try:
        for module in ("fastapi", "uvicorn", "plotly"):
            optional_import(module, "monitor", "the scan monitor (monitor=true)")
    except MissingExtraError as exc:  # a user error before anything moves (scripts/scan.py: exit 2)
        raise MonitorError(str(exc)) from None
    check_port(host, port)
    scan_path = Path(scan_path)
    process = subprocess.Popen([sys.executable, "-m", "dipnet.monitor", str(scan_path), "--wait", "--host", host,
                                "--port", str(port), "--nice", str(NICE), *options])
    try:
        with MonitorJournal(scan_path) as journal:
            yield journal
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
        log.info("monitor stopped; to look at the scan again: python scripts/monitor.py %s", scan_path.parent)
