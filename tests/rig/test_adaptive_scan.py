"""Adaptive scanning on the fake rig: the loop drives the scan runner and resumes with the same plan."""

from __future__ import annotations

import numpy as np
import pytest

from dipnet.planning.adaptive import AdaptiveSettings
from dipnet.core.grid import Grid
from dipnet.core.orientations import Reach
from dipnet.simulator.physics import Tank
from dipnet.planning.planner import NextBestDipPlanner
from dipnet.core.rawscan import RawScanFileError, ScanHeader, read_rawscan
from dipnet.rig.adaptive import adaptive_scan
from dipnet.rig.fake.world import FakeRig
from dipnet.rig.grbl import GrblController
from dipnet.rig.runner import ScanAborted, ScanRunner
from dipnet.core.orientations import direction_to_rig
from dipnet.rig.sensors import AveragingSensor, LineSensor
from dipnet.shapes import builtin_shape
from dipnet.solvers.minnorm import MinNormSolver

AREA = 20000.0
ORIGIN = 50.0
PROTOCOL = {"start_mm": 0.0, "stop_mm": 100.0, "step_mm": 10.0, "safe_mm": 0.0, "origin_height_mm": ORIGIN}
REACH = Reach(tilt_range_deg=(0, 35), step_deg=10)


@pytest.fixture(scope="module")
def world():
    return FakeRig(builtin_shape("box", 3, 40.0), tank=Tank(cross_section_mm2=AREA),
                   origin_height_mm=ORIGIN).register("adaptiverig")


def scan(world, path, budget=8, reach=REACH, planner=None, protocol=None):
    def make_runner(plan, home):
        ctl = GrblController(world.url("grbl"), timeout=0.3, move_timeout=2.0)
        sensor = AveragingSensor(LineSensor(world.url("level"), pattern=r"L=(?P<value>[-+\d.]+)\s*(?P<unit>mm)"),
                                 n=1, max_spread=0.05)
        header = ScanHeader(quantity="level_mm", tank_cross_section_mm2=AREA, step_mm=plan.step_mm,
                            resolution=0.001, rig="fake-grbl")
        return ScanRunner(ctl, sensor, plan, path, header, home=home, progress=False, fsync=False)

    return adaptive_scan(make_runner, protocol or PROTOCOL, path, Grid(16, 3), MinNormSolver(progress=False),
                         planner or NextBestDipPlanner(resolution=16, n_samples=32), reach,
                         AdaptiveSettings(budget=budget, batch_size=2, initial_dips=4))


def test_adaptive_rig_scan_respects_the_reach_and_resumes_with_the_same_plan(world, tmp_path):
    world.reset()
    clean = scan(world, tmp_path / "clean.jsonl")
    assert clean.measurement.n_orientations == 8 and clean.stop_reason == "budget"
    recorded = read_rawscan(tmp_path / "clean.jsonl")
    tilt, _ = direction_to_rig(recorded.directions())
    assert len(recorded.completed()) == 8 and tilt.max() <= 35 + 1e-6

    world.reset(faults=[{"kind": "reset", "at_move": 80}])  # during the second batch
    with pytest.raises(ScanAborted):
        scan(world, tmp_path / "resumed.jsonl")
    assert world.fired
    assert 4 <= len(read_rawscan(tmp_path / "resumed.jsonl").completed()) < 8
    world.reset()
    resumed = scan(world, tmp_path / "resumed.jsonl")  # the same call again
    again = read_rawscan(tmp_path / "resumed.jsonl")
    assert [o.k for o in again.orientations] == list(range(8)) and all(o.complete for o in again.orientations)
    assert np.allclose(again.directions().numpy(), recorded.directions().numpy())
    assert np.allclose(resumed.measurement.profiles.numpy(), clean.measurement.profiles.numpy(), atol=1e-6)


def test_a_changed_reach_does_not_mix_with_the_recorded_plan(world, tmp_path):
    world.reset()
    scan(world, tmp_path / "scan.jsonl", budget=6)
    with pytest.raises(RawScanFileError, match=r"dip 0 was recorded .* outside the rig's reach now"):
        scan(world, tmp_path / "scan.jsonl", budget=8, reach=Reach(tilt_range_deg=(40, 80), step_deg=10))


def test_a_replay_that_plans_otherwise_keeps_the_recorded_dips(world, tmp_path):
    # another criterion stands for what another thread count does to a greedy pick
    world.reset()
    scan(world, tmp_path / "scan.jsonl", budget=6)
    first = read_rawscan(tmp_path / "scan.jsonl")
    with pytest.warns(UserWarning, match="the replayed plan differs from the recorded dips .* are kept"):
        resumed = scan(world, tmp_path / "scan.jsonl", budget=8,
                       planner=NextBestDipPlanner(resolution=16, n_samples=32, criterion="variance"))
    again = read_rawscan(tmp_path / "scan.jsonl")
    assert [o.k for o in again.orientations] == list(range(8)) and all(o.complete for o in again.orientations)
    assert np.allclose(again.directions().numpy()[:6], first.directions().numpy())  # nothing re-dipped
    assert resumed.measurement.n_orientations == 8


def test_a_replay_of_dips_all_recorded_with_other_settings_is_refused(world, tmp_path):
    """Before: a replay whose every dip was recorded ran no runner, so the file's header was never compared with
    the run's settings and a scan recorded with another origin height (or geometry, protocol...) replayed silently
    as this one's. Now it stops with the resume's message, before any dip is replayed."""
    world.reset()
    scan(world, tmp_path / "scan.jsonl", budget=6)
    before = (tmp_path / "scan.jsonl").read_bytes()
    world.reset()
    with pytest.raises(RawScanFileError, match=r"cannot resume, the new scan differs from the recorded one in "
                                               r"rig.origin_height_mm \(config.plan.origin_height_mm\) 50.0 -> 40.0"):
        scan(world, tmp_path / "scan.jsonl", budget=6, protocol={**PROTOCOL, "origin_height_mm": 40.0})
    assert (tmp_path / "scan.jsonl").read_bytes() == before and world.max_lower_seen == 0.0
    again = scan(world, tmp_path / "scan.jsonl", budget=6)  # the recorded settings: replays
    assert again.measurement.n_orientations == 6 and world.max_lower_seen == 0.0


@pytest.mark.slow
def test_scan_script_runs_an_adaptive_scan(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "scan.py"
    overrides = ["+planner=adaptive", "+reach=authors_rig", "planner.budget=5", "planner.batch_size=2",
                 "planner.initial_dips=3", "+planner.resolution=16", "planner.planner.resolution=16",
                 "protocol.step_mm=10", "fsync=false", "progress=false", "rig.fake.shape.radius=30",
                 f"hydra.run.dir={tmp_path}"]
    done = subprocess.run([sys.executable, str(script), *overrides], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    raw = read_rawscan(tmp_path / "rawscan.jsonl")
    tilt, _ = direction_to_rig(raw.directions())
    assert len(raw.completed()) == 5 and tilt.max() <= 35 + 1e-6


def test_a_file_not_recorded_by_a_rig_scan_is_refused_not_replayed(world, tmp_path):
    """The audit's case: a simulated recording (dips along directions only) in an adaptive scan's place. The replay
    failed with "TypeError: unsupported operand type(s) for -: 'NoneType' and 'float'"; now it is named as no rig
    scan's file before any reconstruction or motion (as :class:`ScanRunner` names it)."""
    from dipnet.core.rawscan import OrientationScan, RawScan

    path = tmp_path / "scan.jsonl"
    dips = [OrientationScan(k=k, direction=d.tolist(), meta={"t_start_mm": -ORIGIN}, stage_mm=[0.0, 10.0, 20.0, 30.0],
                            values=[150.0, 151.0, 152.0, 153.0], time_s=[0.0, 1.0, 2.0, 3.0], complete=True)
            for k, d in enumerate(REACH.uniform(4).numpy())]
    RawScan(header=ScanHeader(tank_cross_section_mm2=AREA, step_mm=10.0, rig="simulator"), orientations=dips).save(path)
    world.reset()
    with pytest.raises(RawScanFileError, match=r"cannot resume, the file was not recorded by a rig scan"):
        scan(world, path)
    assert world.max_lower_seen == 0.0
