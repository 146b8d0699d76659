"""Scan an object on a dipping rig (Hydra entry point).

    python scripts/scan.py                                    # fake GRBL rig + level sensor
    python scripts/scan.py rig=grbl rig.controller.url=/dev/ttyUSB0 rig.sensor_url=/dev/ttyUSB1
    python scripts/scan.py rig=fake_marlin sensor=sics name=test
    python scripts/scan.py +planner=adaptive +reach=authors_rig planner.budget=20   # plan dip by dip
    python scripts/scan.py monitor=true                       # and watch it on http://127.0.0.1:8765/

The raw scan goes to ``scans/<name>/rawscan.jsonl`` (appended and flushed reading by reading).
Run the same command again to resume after the last complete orientation. On a fault, Ctrl-C,
SIGTERM or SIGHUP the runner stops the motion and lifts the object only to a position the
controller confirms (see :mod:`dipnet.rig.runner`); the script exits with code 3 and a one-line
message saying what happened and what to do. A scan directory, scan file or port in use by another
scan, or a rig config that does not fit the board, exits with code 2 (``error: ...``) before
anything moves. ``monitor=true`` serves the live page (:mod:`dipnet.monitor`) while the scan runs, in a
separate process; a port in use exits with code 2 before anything moves.
"""

from __future__ import annotations

import logging
import sys
from contextlib import nullcontext
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from dipnet.jobs.cli import run_hydra, user_errors
from dipnet.core.locks import run_directory_lock
from dipnet.jobs.scan import scan_job
from dipnet.rig.runner import ScanAborted

log = logging.getLogger("dipnet")


@hydra.main(version_base="1.3", config_path="pkg://dipnet.conf", config_name="scan")
def main(cfg: DictConfig) -> None:
    path = Path(HydraConfig.get().runtime.output_dir) / "rawscan.jsonl"
    with user_errors(), run_directory_lock(path.parent), monitoring(cfg, path) as journal:
        try:
            scan = scan_job(cfg, path, journal=journal)
        except ScanAborted as exc:
            log.error("%s", exc)
            if journal is not None:
                journal.stopped(str(exc))
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(3) from None
    n = sum(o.n_readings for o in scan.orientations)
    log.info("scan complete: %d orientations, %d readings in %s", len(scan.completed()), n, path)



def monitoring(cfg: DictConfig, path: Path):
    """The live monitor of the scan (``monitor=true``), yielding its journal; else nothing (``None``)."""
    if not cfg.get("monitor", False):
        return nullcontext()
    from dipnet.monitor.launch import scan_monitor

    return scan_monitor(path, port=int(cfg.get("monitor_port", 8765)))


if __name__ == "__main__":
    sys.exit(run_hydra(main))
