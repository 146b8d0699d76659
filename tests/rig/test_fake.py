"""The real drivers, sensors and scan runner against the fake rig (fakerig:// and socket:// URLs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.evaluation.metrics import iou
from dipnet.operators import make_operator
from dipnet.core.orientations import rig_to_direction
from dipnet.simulator.physics import solve_dip
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import ScanHeader, read_rawscan
from dipnet.rig.fake.server import serve
from dipnet.rig.grbl import GrblController
from dipnet.rig.runner import ScanAborted, ScanRunner
from dipnet.core.orientations import direction_to_rig
from dipnet.rig.controller import RigTimeout
from dipnet.rig.sensors import LineSensor, ModbusLevelSensor, SensorError
from dipnet.solvers.minnorm import MinNormSolver
from rig_helpers import AREA, make_world, plan_for, scan



@pytest.fixture(scope="module")
def world(meshes_dir):
    return make_world(meshes_dir, "testrig")


def test_direction_rig_round_trip():
    tilt, spin = np.array([0.0, 10.0, 35.0, 80.0]), np.array([0.0, 20.0, 300.0, 123.0])
    t2, s2 = direction_to_rig(rig_to_direction(tilt, spin))
    assert np.allclose(t2, tilt) and np.allclose(s2[1:], spin[1:])


def test_fake_physics_matches_solve_dip(world):
    world.reset()
    for lower, tilt, spin in ((40.0, 0.0, 0.0), (55.0, 30.0, 70.0), (95.0, 60.0, 10.0)):
        world.start_move({"lower_mm": lower, "tilt_deg": tilt, "spin_deg": spin})
        state = solve_dip(world.shape, rig_to_direction(tilt, spin)[0].numpy(), world.tank, np.array([lower]),
                          world.waterline_start(tilt))
        assert world.rise_mm() == pytest.approx(state.rise_mm[0], abs=2e-4)


@pytest.mark.parametrize("dialect,sensor", [("grbl", "level"), ("marlin", "level"),
                                            *(pytest.param("grbl", s, marks=pytest.mark.slow) for s in ("modbus", "ad", "sics"))])
def test_scan_reconstructs_mesh(world, tmp_path, dialect, sensor):
    world.reset()
    raw = scan(world, dialect, sensor, plan_for(30), tmp_path / "scan.jsonl")
    assert len(raw.completed()) == 30 and world.position().lower_mm == 0.0
    stored = read_rawscan(tmp_path / "scan.jsonl")
    assert stored.header.quantity == ("mass_g" if sensor in ("ad", "sics") else "level_mm")
    assert stored.header.config["controller"]["dialect"] == dialect
    grid = Grid(32, extent=100.0)
    m = preprocess(stored, grid=grid, t_start="metadata")
    assert m.volume_estimate() == pytest.approx(world.shape.volume, rel=0.01)
    rec = MinNormSolver(progress=False).solve(m, make_operator(grid, m.directions, 32))
    truth = world.shape.occupancy(grid, supersample=2).numpy() >= 0.5
    assert iou(rec.binary, truth) >= 0.85


def test_socket_server_mode(world, tmp_path):
    world.reset()
    reference = scan(world, "grbl", "level", plan_for(2, step=10.0), tmp_path / "local.jsonl")
    world.reset()
    with serve(world, ["grbl", "level"]) as server:
        assert server.urls["grbl"].startswith("socket://127.0.0.1:")
        ctl = GrblController(server.urls["grbl"], timeout=1.0)
        sensor = LineSensor(server.urls["level"], pattern=r"L=(?P<value>[-+\d.]+)")
        plan = plan_for(2, step=10.0)
        header = ScanHeader(quantity="level_mm", tank_cross_section_mm2=AREA, step_mm=10.0)
        raw = ScanRunner(ctl, sensor, plan, tmp_path / "remote.jsonl", header, progress=False, fsync=False).run()
    assert len(raw.completed()) == 2
    for a, b in zip(reference.orientations, raw.orientations):
        assert np.allclose(a.values, b.values) and np.allclose(a.stage_mm, b.stage_mm)


def test_marlin_resend_is_recovered(world, tmp_path):
    world.reset(faults=[{"kind": "resend", "at_move": 5}])
    raw = scan(world, "marlin", "level", plan_for(1, step=10.0), tmp_path / "scan.jsonl")
    assert len(raw.completed()) == 1 and world.fired and world.fired[0].kind == "resend"


# faults after which the position is still trustworthy (ALARM:2 keeps it; GRBL asks for a reset); a
# disconnect loses it (tests/rig/test_safety.py)
FAULT_CASES = [("grbl", k) for k in ("drop", "error", "alarm", "unstable", "hold", "late_ok")] + \
              [("marlin", k) for k in ("drop", "error")]


@pytest.mark.parametrize("dialect,kind", FAULT_CASES)
def test_fault_stops_safely_and_keeps_readings(world, tmp_path, dialect, kind):
    plan = plan_for(3, step=5.0)  # 21 readings and 25 moves per orientation
    world.reset()
    clean = scan(world, dialect, "level", plan, tmp_path / "clean.jsonl")
    world.reset(faults=[{"kind": kind, "at_move": 40, "code": 2, "delay_s": 0.6}])
    with pytest.raises(ScanAborted) as info:
        scan(world, dialect, "level", plan, tmp_path / "faulty.jsonl", move_timeout=0.4)
    message = str(info.value)
    assert "\n" not in message and "resume" in message
    assert "object lifted: the controller reports lower 0.000 mm" in message.replace("-0.000", "0.000")
    assert world.fired and world.fired[0].kind == kind
    assert world.position().lower_mm == pytest.approx(plan.safe_mm) and not world.moving()
    assert world.max_lower_seen > plan.start_mm  # the fault hit while the object was dipped
    if kind == "hold":  # reported where the hold stopped the lowering (half-way from 50 to 55 mm)
        assert "feed hold" in message and "Hold:1 at lower 52.500 mm" in message
    kept = read_rawscan(tmp_path / "faulty.jsonl")
    assert kept.complete_orientations() == [0]
    partial = kept.orientations[-1]
    assert partial.k == 1 and not partial.complete and partial.n_readings >= 1
    ref = clean.orientations[1]
    n = partial.n_readings - (kind == "unstable")  # the unstable reading is kept, flagged
    assert np.array_equal(partial.stage_mm[:n], ref.stage_mm[:n]) and np.allclose(partial.values[:n], ref.values[:n])
    if kind == "unstable":
        assert partial.flags[-1] == ["unstable"]


def test_kill_and_resume_equals_uninterrupted(world, tmp_path):
    plan = plan_for(4, step=5.0)
    world.reset()
    clean = scan(world, "grbl", "modbus", plan, tmp_path / "clean.jsonl")
    world.reset(faults=[{"kind": "disconnect", "at_move": 60}])
    with pytest.raises(ScanAborted, match="RigDisconnected"):
        scan(world, "grbl", "modbus", plan, tmp_path / "resumed.jsonl")
    first = read_rawscan(tmp_path / "resumed.jsonl")
    assert 0 < len(first.completed()) < 4
    resumed = scan(world, "grbl", "modbus", plan, tmp_path / "resumed.jsonl")  # the same command again
    assert [o.k for o in resumed.orientations] == [0, 1, 2, 3] and all(o.complete for o in resumed.orientations)
    # each run recorded what it connected to, and where it started
    sessions = read_rawscan(tmp_path / "resumed.jsonl").sessions
    assert [s["first_k"] for s in sessions] == [0, len(first.completed())]
    assert all(s["controller"]["firmware"] == "1.1h" and any("VER:1.1h" in line for line in s["controller"]["build"])
               and s["sensor"]["kind"] == "ModbusLevelSensor" for s in sessions)
    grid = Grid(24, extent=100.0)
    a = preprocess(read_rawscan(tmp_path / "clean.jsonl"), grid=grid, t_start="metadata")
    b = preprocess(read_rawscan(tmp_path / "resumed.jsonl"), grid=grid, t_start="metadata")
    assert torch.allclose(a.directions, b.directions) and torch.allclose(a.profiles, b.profiles)
    # a finished scan run again does nothing
    again = scan(world, "grbl", "modbus", plan, tmp_path / "resumed.jsonl")
    assert sum(o.n_readings for o in again.orientations) == sum(o.n_readings for o in clean.orientations)


def test_scan_config_runs_through_hydra(tmp_path):
    from hydra import compose, initialize_config_module

    from dipnet.jobs.scan import scan_from_config

    overrides = ["rig=fake_marlin", "sensor=sics", "n_dips=2", "protocol.step_mm=10", "fsync=false",
                 "progress=false", "rig.fake.shape.radius=30"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="scan", overrides=overrides)
    raw = scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    assert len(raw.completed()) == 2
    stored = read_rawscan(tmp_path / "rawscan.jsonl")
    assert stored.header.quantity == "mass_g" and stored.header.rig == "fake-marlin"
    assert stored.orientations[0].meta["t_start_mm"] == -cfg.rig.origin_height_mm
    assert stored.header.config["scan"]["sensor"]["device"]["style"] == "sics"


def test_stock_3axis_preset_works_out_of_the_box(meshes_dir, tmp_path):
    from hydra import compose, initialize_config_module

    from dipnet.jobs.scan import scan_from_config

    overrides = ["rig=grbl_3axis", "rig.controller.url=fakerig://stock3/grbl", "rig.sensor_url=fakerig://stock3/level",
                 "rig.controller.timeout=0.3", "n_dips=3", "protocol.step_mm=20", "fsync=false",
                 "progress=false"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="scan", overrides=overrides)
    # a factory-set 3-axis board: no homing ($22=0), no soft limits, MPos in reports
    world = make_world(meshes_dir, "stock3", status_axes="XYZ", axes=dict(cfg.rig.controller.axes),
                       grbl_settings={22: 0})
    assert not world.alarm
    raw = scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    assert len(raw.completed()) == 3 and world.position().lower_mm == 0.0
    assert raw.header.config["controller"]["status_axes"] == "XYZ"


def test_modbus_sensor_reads_real_frames_and_reports_faults(world):
    world.reset()
    good = ModbusLevelSensor(world.url("modbus"), data_type="int32", scale=0.001, timeout=0.2)
    good.connect()
    assert good.read().value == pytest.approx(world.tank.rest_level_mm, abs=1e-3)
    good.close()
    wrong_register = ModbusLevelSensor(world.url("modbus"), address=7, timeout=0.2)  # exception 2 from the slave
    wrong_register.connect()
    with pytest.raises(SensorError, match="IllegalRequestError"):
        wrong_register.read()
    wrong_register.close()
    wrong_slave = ModbusLevelSensor(world.url("modbus"), slave=9, timeout=0.1)  # a real slave stays silent
    wrong_slave.connect()
    with pytest.raises(RigTimeout):
        wrong_slave.read()
    wrong_slave.close()
