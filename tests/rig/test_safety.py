"""Safe-stop policy, protocol resynchronisation, locks and signals, against the fake rig."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dipnet.core.rawscan import ScanHeader, read_rawscan
from dipnet.core.rawscan_writer import RawScanLocked, RawScanWriter
from dipnet.rig.controller import Axis, AxisMap, ControllerError, PortBusy, PortLock, PositionUnknown, RigTimeout
from dipnet.rig.fake.server import serve
from dipnet.rig.grbl import GrblController
from dipnet.rig.runner import RigConfigError, ScanAborted, ScanPlan, plan_orientations
from dipnet.rig.sensors import Reading
from rig_helpers import make_runner, make_sensor, make_world, plan_for, scan


@pytest.fixture(scope="module")
def world(meshes_dir):
    return make_world(meshes_dir, "safetyrig")


def grbl(world, **options) -> GrblController:
    ctl = GrblController(world.url("grbl"), timeout=0.3, move_timeout=options.pop("move_timeout", 1.0), **options)
    ctl.connect()
    return ctl


@pytest.mark.parametrize("dialect,kind", [("grbl", "reset"), ("grbl", "alarm"), ("marlin", "alarm"),
                                          ("marlin", "reset"), ("grbl", "disconnect"), ("marlin", "disconnect")])
def test_position_loss_stops_without_moving_and_blocks_resume(world, tmp_path, dialect, kind):
    plan, path = plan_for(2, step=5.0), tmp_path / "scan.jsonl"
    world.reset(faults=[{"kind": kind, "at_move": 40, "code": 1}])  # GRBL ALARM:1: hard limit
    with pytest.raises(ScanAborted) as info:
        scan(world, dialect, "level", plan, path)
    message = str(info.value)
    assert "OBJECT NOT LIFTED" in message and "home" in message and "lifted:" not in message
    depth = world.position().lower_mm
    assert depth >= 50.0 and not world.moving()  # nothing moved after the fault
    assert path.with_name(path.name + ".position-lost.json").exists()
    # resuming without homing refuses before anything moves
    with pytest.raises(ScanAborted, match="nothing had moved.*") as info:
        scan(world, dialect, "level", plan, path, home=False)
    assert "previous run lost the position" in str(info.value) and "home=true" in str(info.value)
    assert world.position().lower_mm == depth
    # homing re-establishes the position: the scan resumes and completes
    raw = scan(world, dialect, "level", plan, path, home=True)
    assert len(raw.completed()) == 2 and not path.with_name(path.name + ".position-lost.json").exists()


def test_rehome_on_fault_lifts_after_homing(world, tmp_path):
    world.reset(faults=[{"kind": "reset", "at_move": 40}])
    with pytest.raises(ScanAborted, match="object lifted: the controller reports lower 0.000 mm"):
        scan(world, "grbl", "level", plan_for(2, step=5.0), tmp_path / "scan.jsonl", rehome_on_fault=True)
    assert world.position().lower_mm == 0.0


def test_alarm2_gets_the_reset_grbl_asks_for(world):
    world.reset()
    world.grbl_settings.update({20: 1})  # soft limits: machine space [-200, 0]
    try:
        ctl = grbl(world)
        ctl.home()
        with pytest.raises(Exception, match="ALARM:2"):
            ctl.move_to(lower_mm=-10.0)  # Z +10: outside the machine space
        assert ctl.needs_reset and ctl.position_lost is None
        with pytest.raises(Exception, match="waits for a reset"):
            ctl.status()  # GRBL is silent, even to '?'
        position = ctl.settle()  # reset, then $X: ALARM:2 keeps the position
        assert position.lower_mm == pytest.approx(0.0) and ctl.status().state == "Idle"
        ctl.close()
    finally:
        world.grbl_settings.update({20: 0})


def test_late_ok_is_attributed_to_its_own_command(world):
    world.reset(faults=[{"kind": "late_ok", "at_move": 1, "delay_s": 0.5}])
    ctl = grbl(world, move_timeout=0.2)
    ctl.home()
    ctl.move_to(lower_mm=30.0)
    with pytest.raises(Exception, match="did not finish"):
        ctl.wait_idle()
    assert [line for _, line in ctl.unacked] == ["G4 P0"]
    assert ctl.settle().lower_mm == pytest.approx(30.0)  # waits for the late ok: resynchronised
    assert ctl.late == ["G4 P0 -> ok"] and not ctl.unacked
    ctl.move_to(lower_mm=0.0)
    ctl.wait_idle()
    assert ctl.position().lower_mm == pytest.approx(0.0)
    ctl.close()


def test_lost_reply_resynchronises_with_an_idle_reset(world):
    world.reset(faults=[{"kind": "drop", "at_move": 1}])
    ctl = grbl(world)
    ctl.home()
    with pytest.raises(Exception, match="no reply"):
        ctl.move_to(lower_mm=20.0)
    assert ctl.settle().lower_mm == pytest.approx(20.0) and not ctl.unacked
    assert ctl.position_lost is None and not world.alarm  # idle reset: the position is kept
    ctl.close()


@pytest.mark.parametrize("kind", ["corrupt_status", "split_status"])
def test_corrupted_status_is_queried_again(world, tmp_path, kind):
    plan = plan_for(1, step=10.0)
    world.reset()
    clean = scan(world, "grbl", "level", plan, tmp_path / "clean.jsonl")
    world.reset(faults=[{"kind": kind, "at_move": 5}])
    raw = scan(world, "grbl", "level", plan, tmp_path / "faulty.jsonl")
    assert world.fired[0].kind == kind
    assert np.array_equal(raw.orientations[0].values, clean.orientations[0].values)


def test_homing_disabled_gives_error5_and_config_check(world):
    world.reset()
    world.grbl_settings.update({22: 0, 10: 0})
    try:
        with pytest.raises(ControllerError, match="status_axes='XYZ'.*rig=grbl_3axis"):
            grbl(world, status_axes="XYZ")  # the board reports 5 coordinates
        ctl = grbl(world, axes={"tilt": {"letter": "C"}})
        with pytest.raises(ControllerError, match=r"homing is disabled on the board \(\$22=0\)"):
            ctl.home()
        problems = ctl.check_board(True, {"lower": (0.0, 100.0), "tilt": (0.0, 90.0), "spin": (0.0, 350.0)})
        ctl.close()
    finally:
        world.grbl_settings.update({22: 1, 10: 1})
    text = " | ".join(problems)
    assert len(problems) == 3, text  # C not reported, $10=0 (WPos), home with $22=0
    assert "tilt axis is on C" in text and "$10=0" in text and "$22=0" in text


def test_soft_limit_travel_check():
    from dipnet.rig.grbl_dialect import check_settings

    settings = {10: 1, 20: 1, 22: 1, 130: 200.0, 131: 400.0, 132: 100.0}
    axes = AxisMap(lower=Axis("Z", sign=-1), tilt=Axis("X"), spin=Axis("Y"))
    ranges = {"lower": (0.0, 110.0), "tilt": (0.0, 90.0), "spin": (0.0, 350.0)}
    problems = check_settings(settings, "XYZ", axes, True, ranges)
    assert len(problems) == 3 and all("soft limits" in p for p in problems)  # Z to -110, X/Y positive
    fitted = AxisMap(lower=Axis("Z", sign=-1), tilt=Axis("X", sign=-1), spin=Axis("Y", offset=-360.0))
    ranges["lower"] = (0.0, 100.0)
    assert check_settings(settings, "XYZ", fitted, True, ranges) == []


def test_rotary_axis_takes_the_short_way(world):
    world.reset()
    axes = {"spin": {"letter": "B", "wrap": 360.0}}
    world.axes = AxisMap.from_config(axes)
    ctl = grbl(world, axes=axes)
    ctl.home()
    for target, machine in ((350.0, -10.0), (10.0, 10.0), (170.0, 170.0), (320.0, 320.0), (20.0, 380.0)):
        ctl.move_to(spin_deg=target)
        ctl.wait_idle()
        assert world.machine_position()["B"] == pytest.approx(machine)
    ctl.close()
    world.axes = AxisMap()


class SignalAfter:
    """A sensor that sends ``signum`` to this process at its ``n``-th reading."""

    def __init__(self, sensor, n: int, signum: int) -> None:
        self.sensor, self.n, self.signum, self.count = sensor, n, signum, 0
        self.quantity = sensor.quantity

    def identity(self):
        return self.sensor.identity()

    def read(self) -> Reading:
        self.count += 1
        if self.count == self.n:
            os.kill(os.getpid(), self.signum)
            time.sleep(0.1)  # the handler runs here
        return self.sensor.read()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_stop_safely(world, tmp_path, signum):
    world.reset()
    sensor = SignalAfter(make_sensor(world, "level"), 30, signum)
    runner = make_runner(world, "grbl", sensor, plan_for(2, step=5.0), tmp_path / "scan.jsonl")
    runner.sensor_device = lambda: sensor.sensor.sensor
    before = signal.signal(signum, signal.SIG_DFL)  # SIGHUP is ignored when pytest runs under nohup
    try:
        with pytest.raises(ScanAborted) as info:
            runner.run()
        restored = signal.getsignal(signum)
    finally:
        signal.signal(signum, before)
    message = str(info.value)
    assert f"interrupted ({signal.Signals(signum).name} received)" in message
    assert "object lifted: the controller reports lower" in message and world.position().lower_mm == 0.0
    assert restored is signal.SIG_DFL  # handlers restored
    assert read_rawscan(tmp_path / "scan.jsonl").orientations[-1].n_readings >= 1


def test_an_ignored_hangup_stays_ignored(world, tmp_path):
    """Under ``nohup`` (SIGHUP ignored) a hangup must not end the scan: it runs to the end."""
    world.reset()
    sensor = SignalAfter(make_sensor(world, "level"), 30, signal.SIGHUP)
    runner = make_runner(world, "grbl", sensor, plan_for(2, step=5.0), tmp_path / "scan.jsonl")
    runner.sensor_device = lambda: sensor.sensor.sensor
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        runner.run()
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)
    scan = read_rawscan(tmp_path / "scan.jsonl")
    assert len(scan.orientations) == 2 and all(o.n_readings > 1 for o in scan.orientations)


class FailingSensor(SignalAfter):
    def read(self) -> Reading:
        self.count += 1
        if self.count == self.n:
            raise ValueError("a malformed reply")
        return self.sensor.read()


def test_any_exception_ends_in_the_safe_stop(world, tmp_path):
    world.reset()
    sensor = FailingSensor(make_sensor(world, "level"), 30, 0)
    runner = make_runner(world, "grbl", sensor, plan_for(2, step=5.0), tmp_path / "scan.jsonl")
    runner.sensor_device = lambda: sensor.sensor.sensor
    with pytest.raises(ScanAborted, match="ValueError: a malformed reply; object lifted"):
        runner.run()
    assert world.position().lower_mm == 0.0


def test_noisy_interrupted_and_resumed_scan_equals_uninterrupted(meshes_dir, tmp_path):
    # 0.01 mm: the helper sensor's max_spread of 0.05 mm is 5 sigma; at 0.02 mm (2.5 sigma) about 1 in 5 averages
    # is unstable, and whether a scan got through its retries depended on the seed's draws
    noisy = make_world(meshes_dir, "noisyrig", level_sigma_mm=0.01, seed=7)
    plan = plan_for(3, step=5.0)
    clean = scan(noisy, "grbl", "level", plan, tmp_path / "clean.jsonl")
    noisy.reset(faults=[{"kind": "error", "at_move": 40}])
    with pytest.raises(ScanAborted):
        scan(noisy, "grbl", "level", plan, tmp_path / "resumed.jsonl")
    resumed = scan(noisy, "grbl", "level", plan, tmp_path / "resumed.jsonl")
    assert np.ptp(clean.orientations[0].values[:3]) > 0  # the noise is there
    for a, b in zip(clean.orientations, resumed.orientations):
        assert np.array_equal(a.values, b.values) and np.array_equal(a.stage_mm, b.stage_mm)


def test_second_writer_on_a_scan_file_fails_at_once(tmp_path):
    path = tmp_path / "scan.jsonl"
    first = RawScanWriter(path, ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0))
    first.begin_orientation(0, tilt_deg=0.0, spin_deg=0.0)
    with pytest.raises(RawScanLocked, match="being written by another scan"):
        RawScanWriter(path, ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0))
    for i in range(3):
        first.append_reading(float(i), 150.0 + i, float(i))
    first.complete_orientation()
    first.close()
    assert read_rawscan(path).orientations[0].n_readings == 3  # whole records, nothing truncated


def test_records_stay_whole_under_a_writer_that_ignores_the_lock(tmp_path):
    import json
    import threading

    path = tmp_path / "scan.jsonl"
    writer = RawScanWriter(path, ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0))
    writer.begin_orientation(0, tilt_deg=0.0, spin_deg=0.0)
    rogue = os.open(path, os.O_WRONLY | os.O_APPEND)  # misuse: no flock, appends whole lines

    def misuse():
        for i in range(300):
            os.write(rogue, (json.dumps({"type": "note", "i": i, "pad": "x" * 200}) + "\n").encode())

    thread = threading.Thread(target=misuse)
    thread.start()
    for i in range(300):
        writer.append_reading(float(i), 150.0, float(i), ["x" * 50])
    thread.join()
    writer.close()
    os.close(rogue)
    lines = path.read_text().splitlines()
    records = [json.loads(line) for line in lines]  # every line is one whole JSON record
    assert len(records) == 1 + 1 + 300 + 300 and sum(r["type"] == "reading" for r in records) == 300


def test_second_scan_on_the_same_port_fails_at_once(world, tmp_path):
    world.reset()
    with serve(world, ["grbl", "level"]) as server:
        held = PortLock(server.urls["grbl"])  # a scan in another process holds the controller port
        try:
            with pytest.raises(PortBusy, match="in use by pid"):
                PortLock(server.urls["grbl"])
            ctl = GrblController(server.urls["grbl"], timeout=0.3)
            runner = make_runner(world, "grbl", "level", plan_for(1, step=10.0), tmp_path / "scan.jsonl")
            runner.controller = ctl
            with pytest.raises(PortBusy, match="another scan is running on this rig"):
                runner.run()
        finally:
            held.release()
    assert world.position().lower_mm == 0.0


def test_missing_port_says_nothing_moved(world, tmp_path):
    runner = make_runner(world, "grbl", "level", plan_for(1), tmp_path / "scan.jsonl")
    runner.controller = GrblController(str(tmp_path / "ttyNONE"), timeout=0.3)
    with pytest.raises(ScanAborted) as info:
        runner.run()
    assert "nothing had moved" in str(info.value) and "COULD NOT LIFT" not in str(info.value)


def test_position_unknown_blocks_moves(world):
    world.reset()
    ctl = grbl(world)  # homing enabled: GRBL starts in Alarm after power-up
    with pytest.raises(PositionUnknown, match="alarm state"):
        ctl.move_to(lower_mm=10.0)
    ctl.close()


def test_config_mismatch_fails_before_anything_moves(world, tmp_path):
    world.reset()
    world.grbl_settings.update({22: 0})
    try:
        world.alarm = False
        runner = make_runner(world, "grbl", "level", plan_for(1), tmp_path / "scan.jsonl", home=True)
        with pytest.raises(RigConfigError, match=r"\(1\) home=true but homing is disabled"):
            runner.run()
    finally:
        world.grbl_settings.update({22: 1})
    assert world.motion_count == 0


SCAN_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "scan.py"


@pytest.mark.slow
def test_link_lost_while_lowering_needs_confirmation_to_resume(tmp_path):
    """t4e3 from the command line: the controller's link dies with a lowering under way (the board
    may restart and count from 0); a board without homing can only resume on the operator's word."""
    base = [sys.executable, str(SCAN_SCRIPT), f"hydra.run.dir={tmp_path}", "n_dips=2", "protocol.step_mm=20",
            "fsync=false", "progress=false", "rig.fake.shape.radius=30", "+rig.fake.grbl_settings.22=0"]

    def run(*overrides: str) -> tuple[int, str]:
        done = subprocess.run([*base, *overrides], capture_output=True, text=True, timeout=300)
        return done.returncode, done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""

    fault = "rig.fake.faults=[{kind: disconnect, at_move: 5}]"
    code, line = run(fault)
    assert code == 3 and line.startswith("error: scan stopped at orientation 0") and "OBJECT NOT LIFTED" in line
    assert "lost the link" in line and line.endswith("(after a restart: at its zero)")
    assert "resume with confirm_position=true" in line and "home=true" not in line  # $22=0: homing would fail
    marker = tmp_path / "rawscan.jsonl.position-lost.json"
    assert "lost the link" in marker.read_text()
    code, line = run(fault)  # the same command: refuses before anything moves
    assert code == 3 and "previous run lost the position" in line and "nothing had moved" in line
    assert "confirm_position=true" in line and "run the same command" not in line
    code, line = run("confirm_position=true")
    assert code == 0 and not marker.exists() and len(read_rawscan(tmp_path / "rawscan.jsonl").completed()) == 2


def test_connect_lets_a_move_in_progress_finish(world):
    """t4e2 on the fake: connecting while the machine moves waits for it, then resets it at rest
    (a reset in motion would raise ALARM:3 and lose the position)."""
    world.reset()
    world.alarm, world.move_s = False, 0.6
    try:
        world.start_move({"lower_mm": 30.0})
        ctl = grbl(world, move_timeout=3.0)
        assert not world.alarm and ctl.position_lost is None and ctl.position().lower_mm == pytest.approx(30.0)
        ctl.close()
        world.start_move({"lower_mm": 0.0})
        with pytest.raises(RigTimeout, match="still moving"):
            grbl(world, move_timeout=0.1)  # bounded: gives up without resetting the moving machine
        assert not world.alarm
    finally:
        world.move_s = 0.0


def test_soft_limit_check_sees_the_short_way_round(meshes_dir, tmp_path):
    """t4d on the fake: spin 10 -> 195 deg the short way round crosses the travel limit; the check
    refuses before anything moves, and turning directly scans."""
    axes = {"tilt": {"letter": "A", "sign": -1}, "spin": {"letter": "B", "sign": -1, "wrap": 360.0}}
    limited = make_world(meshes_dir, "softwrap", axes=axes, grbl_settings={20: 1})
    plan = ScanPlan(plan_orientations("grid", tilts=[30.0], spins=[10.0, 195.0]), start_mm=0.0, stop_mm=30.0,
                    step_mm=10.0, origin_height_mm=50.0)
    for wrap in (360.0, None):
        runner = make_runner(limited, "grbl", "level", plan, tmp_path / f"scan-{wrap}.jsonl")
        runner.controller = GrblController(limited.url("grbl"), {**axes, "spin": {**axes["spin"], "wrap": wrap}},
                                           timeout=0.3, move_timeout=2.0)
        if wrap:
            with pytest.raises(RigConfigError, match=r"B -10\.\.165 \(the short way round, wrap=360\): set "
                                                     r"rig.controller.axes.spin.wrap=null"):
                runner.run()
            assert limited.motion_count == 0
        else:
            assert len(runner.run().completed()) == 2
