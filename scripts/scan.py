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
anything moves; so does an option no code reads (``+n_dip=4``: "did you mean n_dips?", checked as
``scripts/reconstruct.py`` checks its own), a grid tilt outside ``[0, max_tilt_deg]``, or a resume with
settings that change what a dip records (:meth:`~dipnet.core.rawscan.ScanHeader.differences`).
``monitor=true`` serves the live page (:mod:`dipnet.monitor`) while the scan runs, in a separate
process; a port in use exits with code 2 before anything moves.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping
from contextlib import nullcontext
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from dipnet.core.counts import is_real, whole_number
from dipnet.core.locks import run_directory_lock
from dipnet.core.orientations import check_grid_angles
from dipnet.core.console import report
from dipnet.jobs.cli import run_hydra, user_errors
from dipnet.jobs.deprecations import upgrade_scan_config
from dipnet.jobs.options import check_overrides, hydra_overrides
from dipnet.jobs.scan import scan_job
from dipnet.rig.runner import ScanAborted

log = logging.getLogger("dipnet")

#: Keys the scan reads that no config file declares, so they are added with ``+``: the tank's name and the
#: calibration file (``+rig.tank=lab-tank-1 +rig.calibration=rig_calibration.yaml``) and free-form metadata.
ADDED_KEYS = ("rig.tank", "rig.calibration", "metadata")
#: The scan's on/off options (``home`` may also be null: home when the board can).
BOOLEAN_OPTIONS = ("home", "rehome_on_fault", "confirm_position", "fsync", "progress", "monitor")


@hydra.main(version_base="1.3", config_path="pkg://dipnet.conf", config_name="scan")
def main(cfg: DictConfig) -> None:
    path = Path(HydraConfig.get().runtime.output_dir) / "rawscan.jsonl"
    with user_errors():
        cfg = upgrade_scan_config(cfg)  # once, with its warnings; the scan job's own upgrade has nothing left to do
        check_scan_options(cfg)
    with user_errors(), run_directory_lock(path.parent), monitoring(cfg, path) as journal:
        try:
            scan = scan_job(cfg, path, journal=journal)
        except ScanAborted as exc:
            report(f"error: {exc}")
            if journal is not None:
                journal.stopped(str(exc))
            raise SystemExit(3) from None
        except KeyboardInterrupt:  # outside the rig runner, which stops a dip safely itself: before the first dip,
            # or while an adaptive scan plans its next batch
            kept = (f"every complete dip is kept in {path}; run the same command again to resume" if path.is_file()
                    else "nothing was recorded yet")
            message = f"scan stopped outside a dip (no dip was in progress): {kept}"
            report(f"interrupted: {message}")
            if journal is not None:
                journal.stopped(message)
            raise SystemExit(130) from None
    n = sum(o.n_readings for o in scan.orientations)
    log.info("scan complete: %d orientations, %d readings in %s", len(scan.completed()), n, path)


def check_scan_options(cfg: DictConfig) -> None:
    """Refuse, before anything moves, a command-line option no scan code reads (``+n_dip=4`` for
    ``n_dips=4``; the check of ``scripts/reconstruct.py``: :func:`~dipnet.jobs.options.check_overrides`,
    with :data:`ADDED_KEYS` allowed), an on/off option (:data:`BOOLEAN_OPTIONS`) given as anything but true or false
    (``home=no``, a string, is true) and a grid of tilts the rig cannot reach
    (:func:`~dipnet.core.orientations.check_grid_angles`); raises ``ValueError`` naming the option."""
    overrides, groups = hydra_overrides()
    check_overrides(cfg, [o for o in overrides if not _adds_a_read_key(o)], groups)
    for key in BOOLEAN_OPTIONS:  # a string is true to Python: home=no homed, confirm_position=off skipped homing
        value = cfg.get(key)
        if not isinstance(value, bool) and not (value is None and key == "home"):
            raise ValueError(f"{key} must be true or false{' or null' if key == 'home' else ''}, got {value!r}; "
                             "nothing moved")
    if not is_real(cfg.get("max_tilt_deg")):  # max_tilt_deg=true spread the dips over 1 deg; abc: "could not convert"
        raise ValueError(f"max_tilt_deg must be a number of degrees (the rig's tilt limit, e.g. 90), got "
                         f"{cfg.get('max_tilt_deg')!r}; nothing moved")
    name = cfg.get("name")  # name=../x wrote the scan outside scans/, name= into scans/ itself, among other scans
    if name is None or not str(name).strip() or Path(str(name)).name != str(name) or str(name) in (".", ".."):
        raise ValueError(f"name must be a plain folder name, the scan's folder scans/<name> (no '/' or '..'), got "
                         f"{name!r}; nothing moved (to write elsewhere, set hydra.run.dir)")
    metadata = cfg.get("metadata")
    if metadata is not None and not isinstance(metadata, Mapping):  # metadata=5: "'int' object is not iterable"
        raise ValueError(f"metadata must be a mapping of free-form notes (e.g. '+metadata={{object: cat}}') or empty, "
                         f"got {metadata!r}; nothing moved")
    if cfg.get("orientations") == "grid":
        check_grid_angles(cfg.get("tilts"), cfg.get("spins"), float(cfg.max_tilt_deg))
    elif cfg.get("tilts") is not None or cfg.get("spins") is not None:
        raise ValueError(f"tilts and spins set a grid plan, but orientations={cfg.get('orientations')}: "
                         "add orientations=grid, or drop them")


def _adds_a_read_key(override: str) -> bool:
    """Whether ``override`` (as typed) sets one of :data:`ADDED_KEYS` or a key below one."""
    key = override.lstrip("+~").split("=", 1)[0]
    return any(key == k or key.startswith(k + ".") for k in ADDED_KEYS)


def monitoring(cfg: DictConfig, path: Path):
    """The live monitor of the scan (``monitor=true``), yielding its journal; else nothing (``None``)."""
    if not cfg.get("monitor", False):
        return nullcontext()
    from dipnet.monitor.launch import scan_monitor

    # monitor_port=abc was "invalid literal for int() with base 10: 'abc'", 8765.5 cut to 8765
    return scan_monitor(path, port=whole_number("monitor_port", cfg.get("monitor_port", 8765), 1))


if __name__ == "__main__":
    sys.exit(run_hydra(main))
