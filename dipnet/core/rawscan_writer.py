"""The raw scan's append-only writer: one JSON line per record, flushed (and fsynced) at once, the file locked.

The format is that of :mod:`dipnet.core.rawscan`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from dipnet.core.locks import HeldLock, LockHeld
from dipnet.core.rawscan import OrientationScan, RawScan, RawScanFileError, ScanHeader, read_rawscan


class RawScanWriter:
    """Append-only writer: one JSON line per record, flushed (and fsynced) at once.

    Args:
        path: the ``.jsonl`` file.
        header: scan metadata; written as the first line of a new file.
        resume: if the file exists, read it (tolerating a truncated last line, which is cut
            off), check that ``header`` is compatible with the stored one, and append. The
            scan read so far is :attr:`scan`; continue at ``writer.scan.next_orientation()``.
        overwrite: if the file exists and ``resume`` is false, replace it (else
            ``FileExistsError``).
        fsync: call ``os.fsync`` after every line (survives power loss, slower).

    The file is locked (:class:`dipnet.core.locks.HeldLock` on ``.<name>.lock``, exclusive, non-blocking,
    on every OS) from opening to :meth:`close`: a second writer on the same file fails at once with
    :class:`RawScanLocked` naming the holder. Every record is
    one ``os.write`` on a file opened with ``O_APPEND``, so even a writer that ignores the lock
    cannot interleave fragments of records.

    Usage::

        with RawScanWriter("scan.jsonl", ScanHeader(tank_cross_section_mm2=6e4, step_mm=1)) as w:
            for k in range(w.scan.next_orientation(), n_orientations):
                w.begin_orientation(k, tilt_deg=..., spin_deg=...)
                for ...: w.append_reading(stage_mm, level_mm, time_s, flags=[])
                w.complete_orientation()
    """

    def __init__(self, path: str | Path, header: ScanHeader, resume: bool = True, *,
                 overwrite: bool = False, fsync: bool = True) -> None:
        self.path = Path(path)
        self.fsync = fsync
        self._current: OrientationScan | None = None
        existed = self.path.exists()
        if existed and not resume and not overwrite:
            raise FileExistsError(f"{self.path} exists: pass resume=True to continue it or overwrite=True")
        self._fd: int | None = None
        self._lock = _lock_scan(self.path)
        try:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND | getattr(os, "O_BINARY", 0), 0o644)
            if existed and resume and os.fstat(self._fd).st_size > 0:
                self.scan = read_rawscan(self.path)
                check_resumable(self.scan, header, self.path)
                position, prefix = _append_position(self.path)
                os.ftruncate(self._fd, position)
                if prefix:
                    _write_all(self._fd, prefix)
            else:
                os.ftruncate(self._fd, 0)
                self.scan = RawScan(header=header, path=self.path)
                self._write(header.to_json())
        except BaseException:
            self.close()
            raise

    # ---------------------------------------------------------------- records
    def begin_orientation(self, k: int, *, direction=None, tilt_deg: float | None = None,
                          spin_deg: float | None = None, meta: dict | None = None) -> None:
        """Start orientation ``k`` (restarting it if it was begun but not completed)."""
        if k in self.scan.complete_orientations():
            raise ValueError(f"orientation {k} is already complete in {self.path}")
        o = OrientationScan(k=int(k), direction=None if direction is None else np.asarray(direction, float),
                            tilt_deg=None if tilt_deg is None else float(tilt_deg),
                            spin_deg=None if spin_deg is None else float(spin_deg), meta=dict(meta or {}))
        self._write(o.orientation_json())
        self.scan.orientations = [x for x in self.scan.orientations if x.k != o.k] + [o]
        self._current = o

    def append_reading(self, stage_mm: float, value: float, time_s: float, flags=()) -> None:
        """Record one reading of the current orientation (stage mm, value, time s, flag names)."""
        o = self._require_current()
        record = {"type": "reading", "k": o.k, "stage_mm": float(stage_mm), "value": float(value),
                  "time_s": float(time_s), "flags": [str(f) for f in flags]}
        self._write(record)
        o._append(stage_mm, value, time_s, record["flags"])

    def record_session(self, info: dict[str, Any]) -> None:
        """Record what a rig run found after connecting (JSON-serialisable ``info``; see the module
        docstring), e.g. ``{"first_k": 3, "controller": {"firmware": "1.1h", ...}}``."""
        self._write({"type": "session", **info})
        self.scan.sessions.append(dict(info))

    def complete_orientation(self) -> None:
        """Mark the current orientation as complete."""
        o = self._require_current()
        self._write({"type": "complete", "k": o.k, "n_readings": o.n_readings})
        o.complete = True
        self._current = None

    # ---------------------------------------------------------------- plumbing
    def close(self) -> None:
        """Close the file and release the lock (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        self._lock.release()

    def __enter__(self) -> "RawScanWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _require_current(self) -> OrientationScan:
        if self._current is None:
            raise RuntimeError("call begin_orientation() first")
        return self._current

    def _write(self, obj: dict) -> None:
        if self._fd is None:
            raise ValueError(f"{self.path} is closed")
        _write_all(self._fd, (json.dumps(obj, allow_nan=False) + "\n").encode("utf-8"))
        if self.fsync:
            os.fsync(self._fd)


class RawScanLocked(RawScanFileError):
    """Another writer (a second scan) holds the raw scan file."""


def check_resumable(recorded: RawScan, header: ScanHeader, path: str | Path) -> None:
    """Raise :class:`RawScanFileError` when a scan with ``header`` may not continue ``recorded`` (read from
    ``path``): other units, or a header field or recorded setting that differs
    (:meth:`~dipnet.core.rawscan.ScanHeader.differences`, named in the message). Reads and writes nothing: a
    resume (:class:`RawScanWriter`) and a replay of recorded dips (:class:`~dipnet.rig.adaptive.RigDips`) both check
    with it."""
    declared = {**header.units, **recorded.units}
    if declared != header.units:
        raise RawScanFileError(f"{path}: cannot resume, the file records in the units {declared}, this scan writes "
                               f"{header.units}")
    differences = recorded.header.differences(header)
    if differences:
        raise RawScanFileError(f"{path}: cannot resume, the new scan differs from the recorded one in "
                               f"{'; '.join(differences)} (recorded -> new): scan with the recorded settings, or "
                               "into another file")


def _lock_scan(path: Path) -> HeldLock:
    """Lock ``path`` exclusively (lock file ``.<name>.lock`` beside it), or raise :class:`RawScanLocked` at once."""
    try:
        return HeldLock(path.with_name(f".{path.name}.lock"))
    except LockHeld as exc:
        raise RawScanLocked(f"{path} is being written by another scan ({exc}): wait for that scan to "
                            f"finish or stop it, or choose another name") from None


def _write_all(fd: int, data: bytes) -> None:
    """One ``os.write`` per record (looping only on a short write, which regular files do not do)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _append_position(path: Path) -> tuple[int, bytes]:
    """Where appending to ``path`` starts, and the bytes to write first.

    A truncated (unparseable) last line is cut off; a complete but unterminated one gets its
    newline.
    """
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    tail = data[end:]
    if not tail.strip():
        return end, b""
    try:
        json.loads(tail)
    except ValueError:
        return end, b""
    return len(data), b"\n"
