"""What the monitor page shows, computed from the followed scan (:mod:`dipnet.monitor.tail`).

:func:`snapshot` turns a :class:`~dipnet.monitor.tail.ScanTail`, its journal and the newest running
reconstruction into one JSON-ready dict: the mode (``live``, ``finished``, ``stopped``, ``replay``) and
what it means, the rig's state, the current orientation and stage, the current dip's level trace and the
trace the reconstruction predicts for it, every orientation (done, in progress, planned), time per dip
and the finish time, and the warnings. Units: mm, s, degrees.
"""

from __future__ import annotations

import math
import os
import re
import socket
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from dipnet.core.orientations import rig_to_direction
from dipnet.core.locks import RUN_LOCK_NAME
from dipnet.monitor.tail import Dip, JournalTail, ScanTail

MODES = ("live", "finished", "stopped", "replay")
#: A level that falls by more than this during a dip (mm) is a warning: the object only goes down.
LEVEL_DROP_MM = 0.05
#: A resting level (first reading of a dip) that moved by more than this since the first dip (mm) is a warning.
BASELINE_DRIFT_MM = 0.5


def writer_alive(scan_path: Path) -> bool:
    """Whether a live process holds the scan file's lock or its run directory's lock: the holder
    files (:mod:`dipnet.core.locks`) name a pid, checked on this host; a holder file left by a dead
    process means the scan died. Reads only: the scan is never blocked."""
    for holder in (scan_path.with_name(f".{scan_path.name}.lock.holder"), scan_path.parent / f"{RUN_LOCK_NAME}.holder"):
        try:
            text = holder.read_text(encoding="utf-8", errors="replace")
        except OSError:
            continue
        found = re.match(r"pid (\d+) on (\S+),", text)
        if found is None or found.group(2) != socket.gethostname() or os.name != "posix":
            return True  # another host or OS: the holder file is all we know
        try:
            os.kill(int(found.group(1)), 0)
        except ProcessLookupError:
            continue
        except PermissionError:
            return True
        return True
    return False


def _plan_entries(tail: ScanTail) -> list:
    plan = (tail.header.config or {}).get("plan") if tail.header is not None else None
    return list((plan or {}).get("orientations") or [])


def planned_orientations(tail: ScanTail) -> list[tuple[float, float]]:
    """The ``(tilt, spin)`` the header's plan lists (empty when the scan records none); an entry without both
    angles (a replayed recording whose orientations give only a direction) is left out."""
    return [(float(t), float(s)) for t, s in _plan_entries(tail) if t is not None and s is not None]


def planned_count(tail: ScanTail) -> int:
    """How many orientations the scan will dip: an adaptive scan's budget (its header lists only the first batch's
    orientations, planned before any dip; later batches are chosen from the dips), else the plan's count (0 when
    the scan records none)."""
    config = (tail.header.config or {}) if tail.header is not None else {}
    planner = (config.get("scan") or {}).get("planner")
    if isinstance(planner, dict) and isinstance(planner.get("budget"), int):
        return int(planner["budget"])
    return len(_plan_entries(tail))


def readings_per_dip(tail: ScanTail) -> int | None:
    """Readings planned per orientation (the plan's start, stop and step), ``None`` if not recorded."""
    plan = (tail.header.config or {}).get("plan") if tail.header is not None else None
    if not plan or not all(key in plan for key in ("start_mm", "stop_mm", "step_mm")):
        return None
    return int(math.floor((plan["stop_mm"] - plan["start_mm"]) / plan["step_mm"] + 1e-9)) + 1


def _direction(dip_or_angles) -> list[float]:
    if isinstance(dip_or_angles, Dip):
        if dip_or_angles.direction is not None:
            d = np.asarray(dip_or_angles.direction, dtype=float)
            return (d / np.linalg.norm(d)).tolist()
        dip_or_angles = (dip_or_angles.tilt_deg, dip_or_angles.spin_deg)
    return rig_to_direction(*dip_or_angles)[0].tolist()


#: The log ``scripts/scan.py`` writes beside its scan (Hydra's job log in the run directory).
SCAN_LOG = "scan.log"
_LOGGED_END = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+)\].*? - (?:(?:error|interrupted): (scan stopped .*)|"
                         r"(scan complete: .*))$")


def logged_end(tail: ScanTail) -> tuple[str, str] | None:
    """``("stopped", message)`` or ``("finished", message)`` from the last end :data:`SCAN_LOG` beside the scan
    records (a safe stop, a Ctrl-C outside a dip, or ``scan complete``: an adaptive scan may end before its budget),
    when logged after the scan's last session began; else ``None``. A scan run without ``monitor=true`` keeps no
    journal: its log holds these."""
    try:
        lines = (tail.path.parent / SCAN_LOG).read_text(errors="replace").splitlines()
    except OSError:
        return None
    started = None
    if tail.sessions and tail.sessions[-1].get("time"):
        try:
            started = datetime.fromisoformat(str(tail.sessions[-1]["time"])).timestamp()
        except ValueError:
            return None
    for line in reversed(lines):
        found = _LOGGED_END.match(line)
        if found:
            logged = datetime.strptime(found.group(1), "%Y-%m-%d %H:%M:%S,%f").astimezone().timestamp()
            if started is not None and logged < started - 1.0:
                return None
            return ("stopped", found.group(2)) if found.group(2) else ("finished", f"finished: {found.group(3)}")
    return None


def _last_run_start(tail: ScanTail) -> float:
    """When the scan's last rig run began (UNIX s, its ``session`` record in the raw scan; ``-inf`` without one). A
    journalled stop before it is an earlier run's: a run resumed without ``monitor=true`` writes no journal session."""
    if not tail.sessions or not tail.sessions[-1].get("time"):
        return -math.inf
    try:
        return datetime.fromisoformat(str(tail.sessions[-1]["time"])).timestamp()
    except ValueError:
        return -math.inf


def mode_of(tail: ScanTail, journal: JournalTail, replay: bool, alive: bool) -> tuple[str, str]:
    """``(mode, what it means)`` (one of :data:`MODES`)."""
    planned, done = planned_count(tail), sum(d.complete for d in tail.dips)
    total = f"{done} of {planned}" if planned else f"{done}"
    if replay:
        return "replay", f"replay of a recorded scan: {total} orientations played back"
    stops = [e for e in journal.events if e.get("type") == "stopped"]
    starts = [e for e in journal.events if e.get("type") == "session"]
    if alive:
        return "live", f"live: the scan is running ({total} orientations done)"
    if stops and (not starts or stops[-1]["time"] >= starts[-1]["time"]) and stops[-1]["time"] >= _last_run_start(tail):
        return "stopped", stops[-1]["message"]
    if tail.error is not None:
        return "stopped", (f"the scan file cannot be read past {tail.error}: a damaged line, which resuming does not "
                           "mend (the reconstruction refuses the file too); repair or cut the file at that line")
    logged = None if planned and done >= planned else logged_end(tail)
    if logged:
        return logged
    if planned and done >= planned or (not planned and done and not tail.truncated
                                             and all(d.complete for d in tail.dips)):
        return "finished", f"finished: {total} orientations recorded"
    cut = "; its last line is cut short" if tail.truncated else ""
    return "stopped", (f"stopped: the scan is not running and did not finish ({total} orientations done{cut}); "
                       f"it left no safe-stop message (in its monitor journal or in {SCAN_LOG} beside it), so it died "
                       "(killed, crashed or lost power): check the rig, then run the same scan command again to resume")


def dip_times(tail: ScanTail) -> tuple[float | None, float | None]:
    """``(seconds per dip, seconds per reading)``: medians over the dips recorded in one run
    (start to start of consecutive orientations: lowering, lift and rotation included)."""
    starts = [d.time_s[0] for d in tail.dips if d.time_s]
    cycles = [b - a for a, b in zip(starts, starts[1:]) if b > a]
    steps = [b - a for d in tail.dips for a, b in zip(d.time_s, d.time_s[1:]) if b > a]
    per_dip = float(np.median(cycles)) if cycles else None
    return per_dip, float(np.median(steps)) if steps else None


def finish_estimate(tail: ScanTail, now: float) -> dict[str, Any]:
    """Time per dip, remaining dips and the estimated finish (UNIX s), from the recorded readings."""
    per_dip, per_reading = dip_times(tail)
    planned, n = planned_count(tail), readings_per_dip(tail)
    done = sum(d.complete for d in tail.dips)
    out: dict[str, Any] = {"per_dip_s": per_dip, "per_reading_s": per_reading, "done": done,
                           "planned": planned or None, "finish_time": None, "remaining_s": None}
    if not planned or per_dip is None:
        return out
    current = tail.dips[-1] if tail.dips and not tail.dips[-1].complete else None
    remaining = (planned - done - (current is not None)) * per_dip
    if current is not None and n is not None and per_reading is not None:
        # to the dip's last reading, then the lift and rotation before the next dip starts
        remaining += max(n - len(current.values), 0) * per_reading + max(per_dip - (n - 1) * per_reading, 0.0)
    out["remaining_s"] = max(remaining, 0.0)
    out["finish_time"] = now + out["remaining_s"]
    return out


def consistency_warnings(tail: ScanTail, resolution: float | None) -> list[str]:
    """What the readings themselves show is wrong: flagged readings, a level falling during a dip
    (a leak, a stuck float), the resting level drifting between dips (evaporation, a leak)."""
    out: list[str] = []
    if tail.header is None or tail.header.quantity != "level_mm":
        return out
    drop_tol = max(LEVEL_DROP_MM, 5 * (resolution or 0.0))
    first = next((d.values[0] for d in tail.dips if d.values), None)
    for d in tail.dips:
        unstable = sum("unstable" in f for f in d.flags)
        if unstable:
            out.append(f"orientation {d.k}: {unstable} reading(s) flagged unstable")
        values = np.asarray(d.values)
        if values.size > 1:
            fall = np.maximum.accumulate(values) - values
            i = int(np.argmax(fall))
            if fall[i] > drop_tol:
                out.append(f"orientation {d.k}: the level fell by {fall[i]:.3g} mm while the object went down "
                           f"(at {d.stage_mm[i]:g} mm): a leak, a stuck sensor or a bad reading?")
        if first is not None and d.values and abs(d.values[0] - first) > BASELINE_DRIFT_MM:
            out.append(f"orientation {d.k}: the resting level is {d.values[0] - first:+.3g} mm from the first dip's "
                       "(evaporation, a leak or a drifting sensor?)")
    return out


def predicted_trace(recon: dict[str, Any] | None, dip: Dip, area: float | None,
                    density: float | None = None) -> list[float] | None:
    """The trace the running reconstruction predicts for ``dip`` at its recorded stages, from the reconstruction's
    cumulative volume ``C(t)`` along the dip's direction: the rise ``delta`` solves ``A delta = C(t_start + s +
    delta)`` (fixed point, ``C' < A``) over the dip's first reading. A level (mm) rises by ``delta``; with the liquid's
    ``density`` (g/mm^3, a balance's scan, quantity ``mass_g``) the reading (g) rises by the displaced water's mass,
    ``density A delta``. ``None`` without a reconstruction, a cross-section or the dip's start height."""
    t0 = dip.meta.get("t_start_mm")
    if recon is None or area is None or t0 is None or not dip.values or dip.tilt_deg is None or dip.spin_deg is None:
        return None   # the reconstruction's curves are keyed by the rig angles
    key = f"{dip.tilt_deg:.6f},{dip.spin_deg:.6f}"
    curve = recon.get("cumulative", {}).get(key)
    if curve is None:
        return None
    edges, cum = np.asarray(recon["edges"]), np.asarray(curve)
    t = float(t0) + np.asarray(dip.stage_mm)
    delta = np.zeros_like(t)
    for _ in range(30):
        delta = np.interp(t + delta, edges, cum, left=0.0, right=cum[-1]) / area
    scale = 1.0 if density is None else density * area
    return (dip.values[0] + scale * (delta - delta[0])).tolist()


def snapshot(tail: ScanTail, journal: JournalTail, *, replay: bool = False, alive: bool = False,
             recon: dict[str, Any] | None = None, now: float | None = None) -> dict[str, Any]:
    """Everything the page shows, JSON-ready (see the module docstring)."""
    now = time.time() if now is None else now
    if tail.header is None:
        why = tail.error or f"{tail.path}: no header line yet (the scan has not started writing)"
        return {"mode": "live" if alive else "stopped", "message": why, "orientations": [], "warnings": [],
                "error": tail.error, "time": now}
    mode, message = mode_of(tail, journal, replay, alive)
    header = tail.header
    current = tail.dips[-1] if tail.dips else None
    recorded = {(round(d.tilt_deg or 0.0, 6), round(d.spin_deg or 0.0, 6)) for d in tail.dips}
    orientations = [{"k": d.k, "tilt": d.tilt_deg, "spin": d.spin_deg, "direction": _direction(d),
                     "status": "done" if d.complete else ("in progress" if d is current and mode in ("live", "replay")
                                                          else "incomplete")} for d in tail.dips]
    orientations += [{"k": k, "tilt": t, "spin": s, "direction": _direction((t, s)), "status": "planned"}
                     for k, (t, s) in enumerate(planned_orientations(tail))
                     if (round(t, 6), round(s, 6)) not in recorded]
    dip = None
    if current is not None:
        dip = {"k": current.k, "tilt": current.tilt_deg, "spin": current.spin_deg, "complete": current.complete,
               "stage_mm": current.stage_mm, "values": current.values, "flags": current.flags,
               "n_planned": readings_per_dip(tail),
               "predicted": predicted_trace(recon, current, header.tank_cross_section_mm2,
                                            header.density_g_per_mm3 if header.quantity == "mass_g" else None)}
    status = journal.status or {}
    stops = {e["message"] for e in journal.events if e.get("type") == "stopped"}
    warnings = [f"{e.get('logger', 'scan')}: {e['message']}" for e in journal.events
                if e.get("type") in ("warning", "error") and e["message"] not in stops]
    warnings += consistency_warnings(tail, header.resolution)
    warnings += [f"reconstruction: {w}" for w in (recon or {}).get("warnings", [])]
    if tail.error:
        warnings.append(f"the scan file cannot be read further: {tail.error}")
    return {
        "mode": mode, "message": message, "time": now, "path": str(tail.path), "rig": header.rig,
        "quantity": header.quantity, "sessions": len(tail.sessions),
        "controller": (tail.sessions[-1].get("controller") or {}).get("dialect") if tail.sessions else None,
        "rig_state": status.get("state") or ("moving or reading" if mode == "live" else mode),
        "where": status.get("where") or _where(current, mode), "report": status.get("report", ""),
        "stage_mm": current.stage_mm[-1] if current is not None and current.stage_mm else None,
        "dip": dip, "orientations": orientations, "timing": finish_estimate(tail, now),
        "n_readings": sum(len(d.values) for d in tail.dips), "warnings": warnings,
        "stopped": message if mode == "stopped" else None,
        "recon": None if recon is None else {key: recon.get(key) for key in ("version", "n_dips", "seconds")},
    }


def _where(dip: Dip | None, mode: str) -> str:
    """The stage of the scan as the raw scan tells it (without a journal)."""
    if dip is None:
        return "connecting, homing or moving to the first orientation"
    angles = f"orientation {dip.k} ({_angles_text(dip)})"
    if dip.complete:
        return f"after {angles}: lifting and rotating" if mode == "live" else f"{angles} done"
    return f"{angles}, reading {len(dip.values)} at {dip.stage_mm[-1]:g} mm" if dip.values else f"{angles}: lowering"


def _angles_text(dip: Dip) -> str:
    """``tilt 45, spin 90``, or the direction when the scan records no rig angles (``direction [0, 0.71, 0.71]``)."""
    if dip.tilt_deg is not None and dip.spin_deg is not None:
        return f"tilt {dip.tilt_deg:g}, spin {dip.spin_deg:g}"
    return "direction [" + ", ".join(f"{x:.3g}" for x in _direction(dip)) + "]"
