"""Replay: a recorded scan written out again, reading by reading, at a chosen speed.

:class:`Replay` reads a recording (a dipnet ``.jsonl`` or the authors' ``.csv``,
:func:`~dipnet.preprocessing.recorded.read_scan`) and writes it to a new raw scan file with the
real writer (:class:`~dipnet.core.rawscan_writer.RawScanWriter`), waiting between readings as the
recording's times say, divided by ``speed``. The monitor follows that file exactly as it follows a
running scan, so a replay shows the page a rig would (the mode says ``replay``).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from dipnet.core.rawscan import RawScan
from dipnet.core.rawscan_writer import RawScanWriter

#: The longest wait between two replayed readings, in recorded seconds (longer pauses are cut).
MAX_GAP_S = 30.0
#: Recorded seconds per reading when the recording has no times (the authors' CSV numbers its rows).
CSV_READING_S = 1.0


def load_recording(path: str | Path) -> RawScan:
    """The recording with its plan recorded in the header (``config.plan.orientations``, the
    ``(tilt, spin)`` of every orientation, and its stage range), so the page shows what is planned."""
    from dipnet.preprocessing.recorded import read_scan

    raw = read_scan(path)
    config = dict(raw.header.config or {})
    if "plan" not in config:
        stages = np.concatenate([o.stage_mm for o in raw.orientations if o.n_readings] or [np.zeros(1)])
        config["plan"] = {"orientations": [[o.tilt_deg, o.spin_deg] for o in raw.orientations]}
        if raw.header.step_mm:
            config["plan"].update(start_mm=float(stages.min()), stop_mm=float(stages.max()), step_mm=raw.header.step_mm)
    raw.header.config = config
    return raw


class Replay:
    """Write ``source`` to ``target`` in a background thread at ``speed`` x the recorded pace.

    Args:
        source: the recording (``.jsonl`` or ``.csv``).
        target: the raw scan file to write (replaced).
        speed: playback speed (2: twice as fast as recorded); ``inf``: as fast as possible.
    """

    def __init__(self, source: str | Path, target: str | Path, speed: float = 1.0) -> None:
        if not speed > 0:
            raise ValueError(f"the replay speed must be positive, got {speed!r}")
        self.raw = load_recording(source)
        self.target, self.speed = Path(target), float(speed)
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="monitor-replay", daemon=True)
        self.csv = Path(source).suffix.lower() == ".csv"

    def start(self) -> "Replay":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _wait(self, recorded_s: float) -> None:
        if np.isfinite(self.speed) and recorded_s > 0:
            self._stop.wait(min(recorded_s, MAX_GAP_S) / self.speed)

    def _run(self) -> None:
        with RawScanWriter(self.target, self.raw.header, resume=False, overwrite=True, fsync=False) as writer:
            for session in self.raw.sessions:
                writer.record_session(session)
            last = None
            for o in self.raw.orientations:
                writer.begin_orientation(o.k, direction=o.direction, tilt_deg=o.tilt_deg, spin_deg=o.spin_deg,
                                         meta=o.meta)
                for i in range(o.n_readings):
                    t = float(o.time_s[i]) * (CSV_READING_S if self.csv else 1.0)
                    self._wait(0.0 if last is None else t - last)
                    if self._stop.is_set():
                        return
                    last = t
                    writer.append_reading(o.stage_mm[i], o.values[i], time.time(), o.flags[i])
                if o.complete:
                    writer.complete_orientation()
        self.finished.set()
