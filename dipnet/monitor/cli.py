"""``scripts/monitor.py``: watch a scan (running or finished) or replay a recording in a browser.

    python scripts/monitor.py scans/demo                       # the scan in scans/demo (live or finished)
    python scripts/monitor.py --replay dipnet/data/real/3cats_fixture_3mm.csv --speed 20
    python scripts/monitor.py scans/demo --host 0.0.0.0        # reachable from the network: token printed

It prints the page's address and serves until Ctrl-C, which stops it with one line ``interrupted: ...``
and exit code 130, as every entry point (:func:`dipnet.core.console.interrupted`); SIGTERM or SIGHUP (how
``scan.py monitor=true`` ends it) with exit code 128 + the signal, its worker stopped; a replay's scratch copy
of the recording is removed then. Exit code 2 with ``error: ...`` when there is no scan to show, the port
is taken or an option is out of range.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

from dipnet.core.optional import MissingExtraError, optional_import
from dipnet.core.rawscan import RawScanFileError
from dipnet.core.console import interrupted
from dipnet.rig.runner import on_signals

DEFAULT_PORT = 8765


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="monitor.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", nargs="?", help="the scan's run directory (scans/<name>) or its rawscan.jsonl")
    p.add_argument("--replay", metavar="FILE", help="play back a recording (.jsonl or the authors' .csv)")
    p.add_argument("--speed", type=float, default=10.0,
                   help="replay speed, x the recorded pace (default 10; inf: at once)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default 127.0.0.1; any other needs the printed access token)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT})")
    p.add_argument("--token", help="the access token for a non-loopback --host (default: a random one)")
    p.add_argument("--every", type=int, default=4, help="re-solve the running reconstruction every N dips (default 4)")
    p.add_argument("--resolution", type=int, default=48,
                   help="voxels per axis of the running reconstruction (default 48)")
    p.add_argument("--extent-mm", type=float, default=None,
                   help="grid side (mm); default from the recording's object or its stage travel")
    p.add_argument("--no-recon", action="store_true", help="no running reconstruction")
    p.add_argument("--nice", type=int, default=0, help="lower this process's priority by N (scan.py monitor=true: 10)")
    p.add_argument("--wait", action="store_true",
                   help="the scan may not have started writing yet (scan.py monitor=true)")
    return p


#: The finest running reconstruction (voxels per axis): the largest grid dipnet solves on two cores is 240^3, and the
#: monitor re-solves its grid every few dips (``--resolution 100000`` was taken, then failed in the background).
MAX_RESOLUTION = 256


def terminated(signum: int, frame) -> None:
    """SIGTERM / SIGHUP handler: exit ``128 + signum`` through ``SystemExit``, so the ``finally`` blocks run (the
    running reconstruction is stopped and its queue released; ``scan.py monitor=true`` ends the monitor so). The
    default handler ended the process at once, leaving the worker's semaphores to the resource tracker's
    "leaked semaphore objects" warning: uvicorn re-raises the signal after its graceful shutdown."""
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        with on_signals(terminated), \
                interrupted(lambda: f"monitor stopped; to show it again: python scripts/monitor.py {shown(args)}"):
            optional_import("fastapi", "monitor", "the scan monitor")
            optional_import("uvicorn", "monitor", "the scan monitor")
            optional_import("plotly", "report", "the scan monitor's page")
            return run(args)
    except (MissingExtraError, RawScanFileError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def shown(args: argparse.Namespace) -> str:
    """What the monitor shows, as its command line gives it (the run directory, or ``--replay FILE``)."""
    return args.run if args.replay is None else f"--replay {args.replay}"


def check_args(args: argparse.Namespace) -> None:
    """Raise :class:`~dipnet.monitor.server.MonitorError` for an option out of range, before anything starts
    (the running reconstruction would otherwise fail later, in the background)."""
    from dipnet.monitor.server import MonitorError

    if not args.every >= 1:
        raise MonitorError(f"--every must be a positive number of dips, got {args.every}")
    if not 4 <= args.resolution <= MAX_RESOLUTION:
        raise MonitorError(f"--resolution must be an integer in [4, {MAX_RESOLUTION}] (voxels per axis of a "
                           f"reconstruction re-solved every --every dips), got {args.resolution}")
    if args.extent_mm is not None and not 0 < args.extent_mm < math.inf:
        raise MonitorError(f"--extent-mm must be a positive number (mm), got {args.extent_mm}")
    if not args.speed > 0:
        raise MonitorError(f"--speed must be positive (inf: at once), got {args.speed}")


def run(args: argparse.Namespace) -> int:
    from dipnet.monitor.replay import Replay
    from dipnet.monitor.server import Monitor, MonitorError, access_token, check_port, find_scan, page_url, serve
    from dipnet.monitor.worker import ReconWorker

    if (args.run is None) == (args.replay is None):
        raise MonitorError("give either a run directory (RUN) or --replay FILE")
    check_args(args)
    check_port(args.host, args.port)  # before anything starts: one clear message
    if args.nice and hasattr(os, "nice"):
        os.nice(args.nice)
    with ExitStack() as cleanup:  # on the way out (Ctrl-C too): the monitor and replay stop, the scratch copy goes
        replay = None
        if args.replay is not None:
            if not Path(args.replay).is_file():
                raise MonitorError(f"recording not found: {args.replay}")
            scratch = cleanup.enter_context(tempfile.TemporaryDirectory(prefix="dipnet-replay-",
                                                                        ignore_cleanup_errors=True))
            path = Path(scratch) / "rawscan.jsonl"
            replay = Replay(args.replay, path, args.speed)
        else:
            path = find_scan(args.run, wait=args.wait)
        worker = None if args.no_recon else ReconWorker(path, every=args.every, resolution=args.resolution,
                                                       extent_mm=args.extent_mm)
        token = access_token(args.host, args.token)
        monitor = Monitor(path, replay=replay is not None, worker=worker)
        if replay is not None:
            replay.start()
            cleanup.callback(replay.stop)
        monitor.start()
        cleanup.callback(monitor.close)
        print(f"monitor of {args.replay or path}: {page_url(args.host, args.port, token)}", flush=True)
        if token:
            print(f"access token: {token} (bound to {args.host}: requests without it are refused)", flush=True)
        serve(monitor, args.host, args.port, token)
    return 0
