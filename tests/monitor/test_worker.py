"""The running reconstruction (dipnet.monitor.worker): the dips so far solved on a grid, the predicted
cumulative volumes reproduce the measured level traces, and the background process sends its results."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from dipnet.monitor.state import predicted_trace
from dipnet.monitor.tail import ScanTail
from dipnet.monitor.worker import ReconWorker, grid_extent, reconstruct_scan, sigint_ignored


def test_the_reconstruction_predicts_the_measured_traces(recorded_scan):
    result = reconstruct_scan(recorded_scan, resolution=20)
    assert result["n_dips"] == 6 and result["resolution"] == 20 and len(result["mesh"]["i"]) > 0
    assert len(result["slices"]["occupancy"]) == 3 and np.asarray(result["slices"]["std"][0]).shape == (20, 20)
    tail = ScanTail(recorded_scan)
    tail.poll()
    rise = [d.values[-1] - d.values[0] for d in tail.dips]
    for dip in tail.dips:        # the fitted volume reproduces its own dips (the torus' whole rise is ~5 mm)
        predicted = np.asarray(predicted_trace(result, dip, tail.header.tank_cross_section_mm2))
        assert np.abs(predicted - np.asarray(dip.values)).max() < 0.05 * max(rise), dip.k


def test_the_grid_is_chosen_around_the_recorded_object(recorded_scan):
    # the fake rig's torus of radius 40 mm fills 0.9 of the working ball
    assert grid_extent(recorded_scan, 48) == 2 * 48 * 40.0 / (0.9 * 46)


@pytest.mark.slow   # a spawned process imports torch: ~10 s
def test_the_worker_process_sends_a_reconstruction(recorded_scan):
    worker = ReconWorker(recorded_scan, every=2, resolution=16, nice=0).start()
    try:
        deadline = time.monotonic() + 120
        while not worker.latest():
            assert time.monotonic() < deadline and worker.process.is_alive(), "no reconstruction came"
            time.sleep(0.2)
        assert worker.error is None and worker.result["n_dips"] == 6 and worker.result["version"] == 1
    finally:
        worker.close()
    assert not worker.process.is_alive()


def test_ctrl_c_is_ignored_while_the_worker_starts():
    previous = signal.getsignal(signal.SIGINT)
    with sigint_ignored():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGINT) is previous


@pytest.mark.slow   # a spawned process imports torch: ~10 s
def test_ctrl_c_to_the_process_group_leaves_the_worker_to_the_monitor(recorded_scan):
    """A terminal's Ctrl-C reached the worker too: it printed a KeyboardInterrupt traceback."""
    worker = ReconWorker(recorded_scan, every=2, resolution=16, nice=0).start()
    os.kill(worker.process.pid, signal.SIGINT)   # while it starts (imports torch), then while it waits
    time.sleep(1.0)
    assert worker.process.is_alive()
    os.kill(worker.process.pid, signal.SIGINT)
    worker.close(timeout=120)
    assert worker.process.exitcode == 0   # ended by the monitor's stop, not by KeyboardInterrupt (1)


def test_a_grid_the_scan_cannot_fill_names_the_monitors_options(recorded_scan):
    """``--resolution`` far finer than the stage step: the update failed naming a job's ``resolution``, which a monitor
    user does not set; the message now names the monitor's ``--resolution`` and ``--extent-mm`` too."""
    from dipnet.monitor.worker import grid_hint

    with pytest.raises(ValueError, match="lower resolution") as failed:
        reconstruct_scan(recorded_scan, resolution=256, extent_mm=10.0)
    assert grid_hint(failed.value, 256, 10.0) == (" (the running reconstruction's grid is the monitor's --resolution "
                                                  "256, --extent-mm 10: change them, or pass --no-recon)")
    assert "--extent-mm not given" in grid_hint(failed.value, 256, None)
    assert grid_hint(ValueError("the scan file is empty"), 256, None) == ""
