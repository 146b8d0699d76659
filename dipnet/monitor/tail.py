"""Reading a raw scan file while it grows: the monitor's only view of a scan.

:class:`ScanTail` keeps a byte offset into a ``rawscan.jsonl`` (:mod:`dipnet.core.rawscan`) and parses
only the complete lines appended since the last :meth:`ScanTail.poll`; a line still being written
(no newline yet) waits for the next poll. The same code follows a scan that runs, one that finished,
one that died mid-line and a replay (:mod:`dipnet.monitor.replay`), and it never writes, locks or
signals anything: the scan cannot be slowed or changed by it.

The scan side may add a journal beside the scan (``<scan>.monitor.jsonl``, written by
:class:`dipnet.monitor.journal.MonitorJournal`): warnings, the rig's status samples and the safe-stop
message, which the raw scan does not record. :class:`JournalTail` follows it the same way.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dipnet.core.rawscan import OrientationScan, RawScanFileError, ScanHeader, _check_direction


def journal_path(scan_path: str | Path) -> Path:
    """The monitor journal beside a raw scan: ``<scan>.monitor.jsonl``."""
    scan_path = Path(scan_path)
    return scan_path.with_name(scan_path.name + ".monitor.jsonl")


class LineTail:
    """The complete lines appended to a file since the last call (a growing JSON Lines file).

    A file that shrank below its complete lines (replaced by a new scan) is read again from its start
    (:attr:`restarted`). A partial last line is read again with what follows it at every call: a resumed scan cuts
    off a line its crash left unfinished (:class:`~dipnet.core.rawscan_writer.RawScanWriter`) and writes on from
    there.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.offset = 0
        self.pending = b""
        self.restarted = False

    def new_lines(self) -> list[tuple[int, str]]:
        """``(byte offset, text)`` of the lines completed since the last call (empty if none)."""
        self.restarted = False
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            return []
        if size < self.offset:
            self.offset, self.restarted = 0, True
        with self.path.open("rb") as f:
            f.seek(self.offset)
            data = f.read()
        lines, start = [], 0
        while (end := data.find(b"\n", start)) >= 0:
            if data[start:end].strip():
                lines.append((self.offset + start, data[start:end].decode("utf-8", errors="replace")))
            start = end + 1
        self.offset += start
        self.pending = data[start:]
        return lines


@dataclass
class Dip:
    """One orientation as the monitor sees it: its readings so far (stage mm, value, time s, flags)."""

    k: int
    tilt_deg: float | None
    spin_deg: float | None
    direction: list[float] | None
    meta: dict
    stage_mm: list[float] = field(default_factory=list)
    values: list[float] = field(default_factory=list)
    time_s: list[float] = field(default_factory=list)
    flags: list[list[str]] = field(default_factory=list)
    complete: bool = False


class ScanTail:
    """A raw scan followed line by line (see the module docstring).

    Attributes:
        header: the scan's header, once its line is there (``None`` before).
        dips: the orientations in file order; a restarted orientation replaces its earlier readings.
        sessions: the rig runs' ``session`` records (a resumed scan has several).
        error: a malformed line (``"<path>:<line offset>: <problem>"``): the monitor says it and stops
            reading, as the reconstruction would refuse the file.
    """

    def __init__(self, path: str | Path) -> None:
        self.lines = LineTail(path)
        self.path = Path(path)
        self.header: ScanHeader | None = None
        self.factors: dict[str, float] = {}
        self.dips: list[Dip] = []
        self.sessions: list[dict[str, Any]] = []
        self.error: str | None = None
        self.n_lines = 0

    def poll(self) -> bool:
        """Read what was appended; ``True`` when anything changed."""
        if self.error is not None:
            return False
        lines = self.lines.new_lines()
        if self.lines.restarted:
            self.__init__(self.path)  # the file was replaced: start over
            lines = self.lines.new_lines()
        for offset, text in lines:
            try:
                self._apply(json.loads(text))
            except (ValueError, KeyError, TypeError) as exc:
                self.error = f"{self.path}: byte {offset}: {exc}"
                break
            self.n_lines += 1
        return bool(lines)

    @property
    def truncated(self) -> bool:
        """The file ends in a partial line (being written, or cut short by a crash)."""
        return bool(self.lines.pending.strip())

    def _apply(self, obj: dict[str, Any]) -> None:
        """One line, refused (``ValueError``) where :func:`~dipnet.core.rawscan.read_rawscan` refuses it, so the
        page never shows as recorded what the reconstruction will not read."""
        if not isinstance(obj, dict) or "type" not in obj:
            raise RawScanFileError("expected a JSON object with a 'type' field")
        kind = obj.get("type")
        if self.header is None:
            if kind != "header":
                raise RawScanFileError(f"the first line must be the header, got type {kind!r}")
            self.header = ScanHeader.from_json(obj)
            self.factors = self.header.unit_factors(obj.get("units"))
        elif kind == "orientation":
            k = int(obj["k"])
            if any(d.k == k and d.complete for d in self.dips):
                raise RawScanFileError(f"orientation {k} is begun again after it was completed")
            angles = [None if obj.get(key) is None else float(obj[key]) * self.factors["angles"]
                      for key in ("tilt_deg", "spin_deg")]
            checked = OrientationScan(k=k, direction=obj.get("direction"), tilt_deg=angles[0], spin_deg=angles[1])
            if checked.direction is not None and checked.direction.shape != (self.header.ndim,):
                raise RawScanFileError(f"direction must have {self.header.ndim} components")
            _check_direction(checked)
            self.dips = [d for d in self.dips if d.k != k] \
                + [Dip(k, *angles, obj.get("direction"), obj.get("meta") or {})]
        elif kind == "reading":
            dip = self._dip(obj)
            stage, value, time_s = (float(obj[key]) * self.factors[unit] for key, unit in
                                    (("stage_mm", "stage"), ("value", "value"), ("time_s", "time")))
            if not np.isfinite([stage, value, time_s]).all():
                raise RawScanFileError("reading holds a non-finite number")
            if dip.stage_mm and stage < dip.stage_mm[-1]:
                raise RawScanFileError(f"orientation {dip.k}: stage {stage:g} mm after {dip.stage_mm[-1]:g} mm: the "
                                       "stage moved backwards (readings out of order?)")
            flags = obj.get("flags", [])
            if not isinstance(flags, list):
                raise RawScanFileError("flags must be a list of strings")
            dip.stage_mm.append(stage)
            dip.values.append(value)
            dip.time_s.append(time_s)
            dip.flags.append([str(f) for f in flags])
        elif kind == "complete":
            dip = self._dip(obj)
            if "n_readings" in obj and int(obj["n_readings"]) != len(dip.values):
                raise RawScanFileError(f"orientation {dip.k} is marked complete with {obj['n_readings']} readings "
                                       f"but {len(dip.values)} were recorded")
            dip.complete = True
        elif kind == "session":
            self.sessions.append({key: value for key, value in obj.items() if key != "type"})
        else:
            raise RawScanFileError(f"unknown record type {kind!r}")

    def _dip(self, obj: dict[str, Any]) -> Dip:
        k = int(obj["k"])
        for dip in reversed(self.dips):
            if dip.k == k:
                if dip.complete:
                    raise RawScanFileError(f"record for orientation {k} after it was completed")
                return dip
        raise RawScanFileError(f"record for orientation {k}, which was never begun")


class JournalTail:
    """The monitor journal beside a scan (:func:`journal_path`), followed like the scan.

    Attributes:
        events: ``warning`` / ``error`` / ``stopped`` / ``session`` records in file order.
        status: the newest ``status`` sample (the runner's stage and the controller's last report).
    """

    def __init__(self, scan_path: str | Path) -> None:
        self.lines = LineTail(journal_path(scan_path))
        self.events: list[dict[str, Any]] = []
        self.status: dict[str, Any] | None = None

    def poll(self) -> bool:
        """Read what was appended; ``True`` when anything changed (a malformed line is skipped: not JSON, not an
        object, or an event without its message or time, which the page needs)."""
        lines = self.lines.new_lines()
        for _, text in lines:
            try:
                obj = json.loads(text)
            except ValueError:
                continue
            if not isinstance(obj, dict) or (obj.get("type") != "status" and not _is_event(obj)):
                continue
            if obj.get("type") == "status":
                self.status = obj
            else:
                self.events.append(obj)
        return bool(lines)


def _is_event(obj: dict[str, Any]) -> bool:
    """A journal event the page can show: a ``session`` with its time, or a warning, error or stop with its
    message and time (:class:`dipnet.monitor.journal.MonitorJournal` writes them so)."""
    kind, when = obj.get("type"), obj.get("time")
    if not isinstance(when, (int, float)) or isinstance(when, bool):
        return False
    return kind == "session" or (kind in ("warning", "error", "stopped") and isinstance(obj.get("message"), str))
