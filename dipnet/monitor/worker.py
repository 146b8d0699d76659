"""The running reconstruction: a background process that re-solves the scan every few dips.

:func:`reconstruct_scan` reads the complete dips of the scan file as the reconstruction job would
(:func:`~dipnet.preprocessing.sources.read_recorded`), checks them
(:func:`~dipnet.preprocessing.validation.validate_measurement`: its warnings go to the page), solves them
on an ``N^3`` grid (default the ``minnorm`` solver: a Cholesky solve) and returns what the page draws: three
central slices of the occupancy and of its posterior standard deviation
(:func:`~dipnet.evaluation.uncertainty.uncertainty`), the surface mesh, and the cumulative volume
``C(t)`` the reconstruction predicts along every orientation the scan records or plans (for the
predicted level trace, :func:`dipnet.monitor.state.predicted_trace`).

:class:`ReconWorker` runs it in a separate process at a lower priority (``nice``), one torch thread,
and sends each result through a queue: the scan never waits for it.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
import traceback
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: The reader's warning that the dip being scanned is left out: the normal state of a running scan.
INCOMPLETE = "are incomplete and left out"
#: Seconds without a new line after which the scan is taken as ended (the last dips are solved then).
QUIET_S = 5.0
#: Grid side (mm) when neither the option nor the recording fixes it: this many times the stage travel.
TRAVEL_EXTENT_FACTOR = 1.3


def grid_extent(path: Path, resolution: int, fill: float = 0.9) -> float:
    """The grid side (mm) around the object: the radius of the object a fake-rig scan names in its header
    (:func:`~dipnet.preprocessing.truth.recorded_shape_spec`, its ``radius``), else
    :data:`TRAVEL_EXTENT_FACTOR` x the stage travel of its readings (the object passes the water line within it)."""
    from dipnet.core.framing import extent_around
    from dipnet.preprocessing.recorded import read_scan
    from dipnet.preprocessing.truth import recorded_shape_spec

    spec = recorded_shape_spec(path) or {}
    if isinstance(spec.get("radius"), (int, float)) and spec["radius"] > 0:
        return extent_around(float(spec["radius"]), resolution, fill)
    raw = read_scan(path)
    stages = np.concatenate([o.stage_mm for o in raw.orientations if o.n_readings] or [np.zeros(1)])
    travel = float(stages.max() - stages.min())
    if not travel > 0:
        raise ValueError(f"{path}: the readings span no stage travel: give the grid extent (--extent-mm)")
    return TRAVEL_EXTENT_FACTOR * travel


def reconstruct_scan(path: str | Path, resolution: int = 48, extent_mm: float | None = None,
                     solver: Any = None) -> dict[str, Any]:
    """Reconstruct the complete dips of the scan file ``path`` (see the module docstring).

    Returns:
        ``{"n_dips", "seconds", "extent_mm", "slices": {"occupancy"|"std": [x, y, z] 2D lists}, "mesh":
        {"x","y","z","i","j","k"}, "edges": (M+1,) mm, "cumulative": {"tilt,spin": (M+1,) mm^3},
        "uncertainty": summary, "warnings": [...]}``.
    """
    import torch

    from dipnet.core.grid import Grid
    from dipnet.core.orientations import rig_to_direction
    from dipnet.evaluation.uncertainty import uncertainty
    from dipnet.monitor.tail import ScanTail
    from dipnet.monitor.state import planned_orientations
    from dipnet.operators import make_operator
    from dipnet.preprocessing.sources import read_recorded
    from dipnet.preprocessing.validation import validate_measurement
    from dipnet.shapes.isosurface import volume_to_mesh
    from dipnet.solvers.minnorm import MinNormSolver

    start = time.perf_counter()
    path = Path(path)
    extent = float(extent_mm) if extent_mm else grid_extent(path, resolution)
    grid = Grid(int(resolution), 3, extent)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        measurement = read_recorded(str(path), grid)
        validate_measurement(measurement, grid)   # its warnings are caught here; an error ends this update
    operator = make_operator(grid, measurement.directions, grid.n)
    recon = (solver or MinNormSolver(progress=False)).solve(measurement, operator)
    maps, summary = uncertainty(recon, measurement, operator, n_samples=16)
    occupancy = recon.occupancy.numpy() if hasattr(recon.occupancy, "numpy") else np.asarray(recon.occupancy)
    binary = recon.binary.astype(np.float32)
    mesh = volume_to_mesh(binary, grid)
    tail = ScanTail(path)
    tail.poll()
    angles = {(d.tilt_deg, d.spin_deg) for d in tail.dips} | set(planned_orientations(tail))
    angles = sorted(a for a in angles if a[0] is not None)
    cumulative: dict[str, list[float]] = {}
    if angles:
        dirs = torch.cat([rig_to_direction(t, s) for t, s in angles])
        fitted = torch.from_numpy(occupancy.astype(np.float32))  # the volume that fits the dips, not its threshold
        cum = make_operator(grid, dirs, grid.n).cumulative(fitted)
        cumulative = {f"{t:.6f},{s:.6f}": [0.0, *np.round(row, 3).tolist()] for (t, s), row in zip(angles, cum.numpy())}
    edges = np.linspace(-extent / 2, extent / 2, grid.n + 1)
    mid = grid.n // 2
    std = maps["std"]
    return {"n_dips": int(measurement.n_orientations), "seconds": time.perf_counter() - start, "extent_mm": extent,
            "resolution": grid.n, "threshold": float(recon.threshold),
            "slices": {name: [np.round(v[mid, :, :], 3).tolist(), np.round(v[:, mid, :], 3).tolist(),
                              np.round(v[:, :, mid], 3).tolist()]
                       for name, v in (("occupancy", occupancy), ("std", _resize(std, occupancy.shape)))},
            "mesh": {"x": np.round(mesh.vertices[:, 0], 2).tolist(), "y": np.round(mesh.vertices[:, 1], 2).tolist(),
                     "z": np.round(mesh.vertices[:, 2], 2).tolist(), "i": mesh.faces[:, 0].tolist(),
                     "j": mesh.faces[:, 1].tolist(), "k": mesh.faces[:, 2].tolist()},
            "edges": np.round(edges, 4).tolist(), "cumulative": cumulative,
            "uncertainty": {k: float(v) for k, v in summary.items()},
            "warnings": list(dict.fromkeys(str(w.message) for w in caught if INCOMPLETE not in str(w.message)))}


def _resize(volume: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``volume`` (a coarser grid) resampled to ``shape`` by nearest neighbour."""
    idx = np.ix_(*[np.minimum((np.arange(n) * volume.shape[i]) // n, volume.shape[i] - 1) for i, n in enumerate(shape)])
    return volume[idx]


def count_complete(path: Path) -> int:
    """Complete dips in the scan file now (a cheap count of its ``complete`` lines)."""
    try:
        return path.read_bytes().count(b'"type": "complete"')
    except OSError:
        return 0


def worker_main(path: str, out: "mp.Queue", every: int, resolution: int, extent_mm: float | None,
                stop: "mp.Event", nice: int, parent: int, poll_s: float = 0.5) -> None:
    """The worker process: re-solve when ``every`` more dips are complete, or when dips were added and the
    file has not grown for :data:`QUIET_S` (the scan finished or stopped); it ends with ``stop`` or when
    its ``parent`` process is gone (killed: nothing else would end it). Ctrl-C is ignored here (see
    :func:`sigint_ignored`; again in case it was started off the main thread)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import torch

    out.cancel_join_thread()   # exit without waiting for the monitor to read the last result (it may be gone)
    if nice and hasattr(os, "nice"):
        os.nice(nice)
    torch.set_num_threads(1)
    done, version = 0, 0
    while not stop.is_set() and os.getppid() == parent:
        n = count_complete(Path(path))
        if n > done and (n - done >= every or done == 0 or quiet(Path(path))):
            try:
                result = reconstruct_scan(path, resolution, extent_mm)
                version += 1
                out.put({**result, "version": version})
            except Exception as exc:  # noqa: BLE001 - the page shows why, the worker goes on
                out.put({"error": f"{type(exc).__name__}: {exc}{grid_hint(exc, resolution, extent_mm)}", "n_dips": n,
                         "trace": traceback.format_exc(limit=3)})
            done = n
        stop.wait(poll_s)


def grid_hint(exc: Exception, resolution: int, extent_mm: float | None) -> str:
    """For a failure whose message asks for another resolution or extent (in a job's terms: ``resolution``,
    ``extent_mm``), the monitor's options that set them; else ``""``."""
    if "resolution" not in str(exc) and "extent_mm" not in str(exc):
        return ""
    extent = f"--extent-mm {extent_mm:g}" if extent_mm else "--extent-mm not given (chosen around the object)"
    return (f" (the running reconstruction's grid is the monitor's --resolution {resolution}, {extent}: change them, "
            "or pass --no-recon)")


def quiet(path: Path) -> bool:
    """The file has not changed for :data:`QUIET_S` seconds."""
    try:
        return time.time() - path.stat().st_mtime > QUIET_S
    except OSError:
        return False


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """Ignore Ctrl-C (SIGINT) in this process for the block, so a process started in it ignores Ctrl-C from its
    first instruction (it inherits that): a terminal sends Ctrl-C to the whole process group, and the monitor
    stops its worker itself (:meth:`ReconWorker.close`), with no traceback from the worker. Only the main
    thread can set signal handlers; elsewhere the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class ReconWorker:
    """The reconstruction process of one monitored scan (start, :meth:`latest`, :meth:`close`).

    Args:
        path: the raw scan file.
        every: re-solve after this many more complete dips.
        resolution: voxels per axis.
        extent_mm: grid side (mm); ``None``: :func:`grid_extent`.
        nice: priority decrease of the process below the monitor's (0: none).
    """

    def __init__(self, path: str | Path, every: int = 4, resolution: int = 48, extent_mm: float | None = None,
                 nice: int = 5) -> None:
        ctx = mp.get_context("spawn")
        self.queue, self.stop = ctx.Queue(), ctx.Event()
        self.process = ctx.Process(target=worker_main, name="dipnet-monitor-recon", daemon=True,
                                   args=(str(path), self.queue, int(every), int(resolution), extent_mm, self.stop, nice,
                                         os.getpid()))
        self.result: dict[str, Any] | None = None
        self.error: str | None = None

    def start(self) -> "ReconWorker":
        with sigint_ignored():
            self.process.start()
        return self

    def latest(self) -> bool:
        """Take the results sent since the last call; ``True`` when a new one arrived."""
        changed = False
        while True:
            try:
                item = self.queue.get_nowait()
            except queue.Empty:
                return changed
            if "error" in item:
                self.error = f"after {item['n_dips']} dips: {item['error']}"
                log.warning("running reconstruction failed %s", self.error)
            else:
                self.result, self.error = item, None
            changed = True

    def close(self, timeout: float = 10.0) -> None:
        self.stop.set()
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(1.0)
