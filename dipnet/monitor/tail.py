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

from dipnet.core.rawscan import RawScanFileError, ScanHeader


def journal_path(scan_path: str | Path) -> Path:
    """The monitor journal beside a raw scan: ``<scan>.monitor.jsonl``."""
    scan_path = Path(scan_path)
    return scan_path.with_name(scan_path.name + ".monitor.jsonl")


class LineTail:
    """The complete lines appended to a file since the last call (a growing JSON Lines file).

    A file that shrank (replaced by a new scan) is read again from its start (:attr:`restarted`).
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
        if size < self.offset + len(self.pending):
            self.offset, self.pending, self.restarted = 0, b"", True
        with self.path.open("rb") as f:
            f.seek(self.offset + len(self.pending))
            data = self.pending + f.read()
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
        kind = obj.get("type")
        if self.header is None:
            if kind != "header":
                raise RawScanFileError(f"the first line must be the header, got type {kind!r}")
            self.header = ScanHeader.from_json(obj)
            self.factors = self.header.unit_factors(obj.get("units"))
        elif kind == "orientation":
            k = int(obj["k"])
            angles = [None if obj.get(key) is None else float(obj[key]) * self.factors["angles"]
                      for key in ("tilt_deg", "spin_deg")]
            self.dips = [d for d in self.dips if d.k != k] + [Dip(k, *angles, obj.get("direction"), obj.get("meta") or {})]
        elif kind == "reading":
            dip = self._dip(obj)
            dip.stage_mm.append(float(obj["stage_mm"]) * self.factors["stage"])
            dip.values.append(float(obj["value"]) * self.factors["value"])
            dip.time_s.append(float(obj["time_s"]) * self.factors["time"])
            dip.flags.append([str(f) for f in obj.get("flags", [])])
        elif kind == "complete":
            self._dip(obj).complete = True
        elif kind == "session":
            self.sessions.append({key: value for key, value in obj.items() if key != "type"})
        else:
            raise RawScanFileError(f"unknown record type {kind!r}")

    def _dip(self, obj: dict[str, Any]) -> Dip:
        k = int(obj["k"])
        for dip in reversed(self.dips):
            if dip.k == k:
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
        """Read what was appended; ``True`` when anything changed (a malformed line is skipped)."""
        lines = self.lines.new_lines()
        for _, text in lines:
            try:
                obj = json.loads(text)
            except ValueError:
                continue
            if obj.get("type") == "status":
                self.status = obj
            else:
                self.events.append(obj)
        return bool(lines)
