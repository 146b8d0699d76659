"""The scan runner (dipnet.rig.runner) on the fake rig: scans that reconstruct the mesh with each driver and
sensor, faults that stop safely and keep the readings, a killed scan resumed to the uninterrupted result."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.rawscan import RawScanFileError, read_rawscan
from dipnet.evaluation.metrics import iou
from dipnet.operators import make_operator
from dipnet.preprocessing.preprocess import preprocess
from dipnet.rig.runner import ScanAborted, ScanPlan, plan_orientations
from dipnet.rig.sensors import AveragingSensor
from dipnet.solvers.minnorm import MinNormSolver

from rig_helpers import plan_for, scan


@pytest.mark.parametrize("dialect,sensor", [("grbl", "level"), ("marlin", "level"),
                                            *(pytest.param("grbl", s, marks=pytest.mark.slow)
                                              for s in ("modbus", "ad", "sics"))])
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


def test_a_resume_with_another_orientation_plan_names_the_options(world, tmp_path):
    """``scan.py n_dips=10`` over a finished 6-dip scan (to add dips): before, "orientation 0 was recorded at (tilt,
    spin) = (23.556464, 0.0), not as planned: use another file", which named neither the cause nor what to do."""
    world.reset()
    scan(world, "grbl", "level", plan_for(3, step=10.0), tmp_path / "scan.jsonl")
    with pytest.raises(RawScanFileError) as info:
        scan(world, "grbl", "level", plan_for(5, step=10.0), tmp_path / "scan.jsonl")
    message = str(info.value)
    assert re.search(r"orientation 0 was recorded at \(tilt, spin\) = \([\d.]+, 0.0\), where this run plans "
                     r"\([\d.]+, 0\) \(5 orientations; the file's plan holds 3 orientations\): the orientation options "
                     r"\(n_dips, orientations, seed, tilts, spins, max_tilt_deg\) differ", message), message
    assert message.endswith("resume with the recorded options, or scan into another file")


def test_a_resume_with_other_metadata_says_the_file_keeps_its_own(world, tmp_path):
    """The audit's case: a finished scan run again with ``+metadata.object=cat`` said "already complete", exit 0,
    and dropped the new metadata without a word. The header is written once: the resume warns, naming the keys."""
    from rig_helpers import make_runner

    world.reset()
    first = make_runner(world, "grbl", "level", plan_for(2, step=20.0), tmp_path / "scan.jsonl")
    first.header.metadata = {"object": "bunny"}
    first.run()
    again = make_runner(world, "grbl", "level", plan_for(2, step=20.0), tmp_path / "scan.jsonl")
    again.header.metadata = {"object": "cat", "operator": "ab"}
    with pytest.warns(UserWarning, match=r"scan.jsonl: resumed with metadata other than its header's \(object, "
                                         r"operator: the file holds \{\"object\": \"bunny\", \"operator\": null\}, "
                                         r"this run gave \{\"object\": \"cat\", \"operator\": \"ab\"\}\).*"
                                         r"scan into another file"):
        again.run()
    assert read_rawscan(tmp_path / "scan.jsonl").header.metadata == {"object": "bunny"}
    same = make_runner(world, "grbl", "level", plan_for(2, step=20.0), tmp_path / "scan.jsonl")
    same.header.metadata = {"object": "bunny"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same.run()


@pytest.mark.parametrize("protocol, message", [
    ({"retries": -1}, r"protocol.retries must be an integer >= 0 .*got -1; nothing moved"),
    ({"settle_s": -1.0}, r"protocol.settle_s must be a number of seconds >= 0, got -1.0; nothing moved"),
    ({"settle_s": float("nan")}, r"protocol.settle_s must be a number of seconds >= 0, got nan"),
])
def test_a_negative_retries_or_settle_time_is_refused_before_anything_moves(protocol, message):
    with pytest.raises(ValueError, match=message):
        ScanPlan([(0.0, 0.0)], start_mm=0.0, stop_mm=30.0, step_mm=10.0, **protocol)


@pytest.mark.parametrize("protocol, message", [
    ({"step_mm": "abc"}, r"protocol.step_mm must be a finite number \(mm\), got 'abc'; nothing moved"),
    ({"step_mm": True}, r"protocol.step_mm must be a finite number \(mm\), got True"),
    ({"stop_mm": "110"}, r"protocol.stop_mm must be a finite number \(mm\), got '110'"),
    ({"start_mm": float("nan")}, r"protocol.start_mm must be a finite number \(mm\), got nan"),
    ({"safe_mm": False}, r"protocol.safe_mm must be a finite number \(mm\), got False"),
    ({"step_mm": -4.0}, r"need step_mm > 0 .* \(protocol.step_mm, protocol.start_mm, protocol.stop_mm, mm\)"),
])
def test_a_protocol_height_that_is_not_a_number_is_refused_naming_the_option(protocol, message):
    """Before: ``scan.py protocol.step_mm=abc`` raised "TypeError: '>' not supported between instances of 'str' and
    'int'" (a traceback), ``protocol.step_mm=true`` scanned with a 1 mm step (True is 1), without a word."""
    with pytest.raises(ValueError, match=message):
        ScanPlan([(0.0, 0.0)], **{"start_mm": 0.0, "stop_mm": 30.0, "step_mm": 10.0, **protocol})


def test_an_unknown_orientation_plan_is_refused_naming_the_option_and_the_grid():
    """Before: ``scan.py orientations=grids`` was refused as "unknown orientation set 'grids'; choose fibonacci, random
    or uniform": no option named, and the scan's grid plan left out of the choices."""
    with pytest.raises(ValueError, match=r"orientations='grids' is not an orientation plan: choose grid \(with tilts "
                                         r"and spins\) or one of fibonacci, random, uniform \(with n_dips\)"):
        plan_orientations("grids", n=4)
    assert len(plan_orientations("uniform", n=4)) == 4


def test_a_step_that_leaves_a_dip_fewer_than_four_readings_is_refused_before_anything_moves():
    """The audit's protocol.step_mm=200 over a 30 mm dip read once per orientation and finished with exit 0;
    a plan of fewer than MIN_READINGS_PER_DIP readings is refused, naming the option. Four are enough."""
    from dipnet.rig.runner import MIN_READINGS_PER_DIP

    with pytest.raises(ValueError, match=r"protocol.step_mm=200 plans 1 reading\(s\) per orientation .* at least 4"):
        ScanPlan([(0.0, 0.0)], start_mm=0.0, stop_mm=30.0, step_mm=200.0)
    assert len(ScanPlan([(0.0, 0.0)], start_mm=0.0, stop_mm=30.0, step_mm=10.0).stages()) == MIN_READINGS_PER_DIP == 4


def test_a_grid_plan_dips_each_pose_once_and_says_so(caplog):
    """Before: ``tilts=[0,30] spins=[0,360]`` planned 4 dips of 2 poses, no word."""
    with caplog.at_level("WARNING", logger="dipnet.rig.runner"):
        assert plan_orientations("grid", tilts=[0, 30], spins=[0, 360]) == [(0.0, 0.0), (30.0, 0.0)]
    [record] = [r for r in caplog.records if r.levelname == "WARNING"]
    assert record.getMessage() == (
        "orientations=grid: 2 of its 4 tilts x spins pairs command the pose of an earlier pair (spins 360 deg apart "
        "are one spin): (0, 360) as (0, 0), (30, 360) as (30, 0); each pose is dipped once, 2 dips")
    caplog.clear()
    with caplog.at_level("WARNING", logger="dipnet.rig.runner"):  # the vertical at two spins: two poses, no word
        assert len(plan_orientations("grid", tilts=[0, 30], spins=[0, 180])) == 4
    assert not caplog.records


class _Readings(AveragingSensor):
    """The fake rig's averaged level sensor ``averaging``, its first readings replaced by ``values`` (mm)."""

    def __init__(self, averaging: AveragingSensor, values) -> None:
        super().__init__(averaging.sensor, averaging.n, averaging.max_spread)
        self.values = list(values)

    def read(self):
        real = super().read()
        return real._replace(value=self.values.pop(0)) if self.values else real


def test_a_reading_that_is_not_a_finite_number_is_retried_and_never_recorded(world, tmp_path):
    """Before: a level of inf (``1e999 mm``) or NaN (a Modbus float32 transducer without an echo) stopped the scan
    with "ValueError: Out of range float values are not JSON compliant" (and a numpy RuntimeWarning); now it counts as
    a failed try, and a sensor that gives nothing else stops the scan naming the value, nothing of it recorded."""
    from rig_helpers import make_sensor

    plan = plan_for(1, step=20.0)
    world.reset()
    raw = scan(world, "grbl", _Readings(make_sensor(world, "level"), [float("nan"), float("inf")]), plan,
               tmp_path / "recovers.jsonl")
    assert raw.orientations[0].complete and np.isfinite(raw.orientations[0].values).all()
    world.reset()
    with pytest.raises(ScanAborted, match=r"reading 0 at 0 mm: SensorError: the sensor gave no finite reading in 3 "
                                          r"tries \(last inf mm\): .*object lifted"):
        scan(world, "grbl", _Readings(make_sensor(world, "level"), [float("inf")] * 3), plan, tmp_path / "inf.jsonl")
    assert read_rawscan(tmp_path / "inf.jsonl").orientations[0].n_readings == 0


def test_a_reading_is_never_recorded_where_the_controller_reports_the_machine_is_not(world, tmp_path, monkeypatch):
    """A GRBL board with a work offset (G54 Z -7 mm, kept in its EEPROM after an operator zeroed Z in a sender) goes
    to ``G0 Z-10`` at machine Z -17 and reports that in MPos. Before: both dips completed, exit 0, every reading
    recorded 7 mm shallower than the object was (at stage 20 mm: 150.301 mm, where the clean scan reads 150.014).
    Now the Idle report after each move is compared with the commanded position: the scan stops after the first
    (the lift to the safe height), before the object is turned or anything is recorded."""
    plan = plan_for(2, step=10.0)
    world.reset()
    real = world.target_from_words

    def work_offset(words: dict[str, float]) -> dict[str, float | None]:
        return real({**words, **({"Z": words["Z"] - 7.0} if "Z" in words else {})})

    monkeypatch.setattr(world, "target_from_words", work_offset)
    with pytest.raises(ScanAborted) as info:
        scan(world, "grbl", "level", plan, tmp_path / "offset.jsonl")
    message = str(info.value)
    assert message.startswith("scan stopped at orientation 0 (tilt 41.4096, spin 0): PositionMismatch: idle after "
                              "the move, the controller reports lower 7.000 mm (commanded 0, Z -7 in MPos): the "
                              "machine is not where the scan sent it, and no reading is recorded there. GRBL moves in "
                              "work coordinates and reports machine ones: clear a work offset (G10 L2 P1 X0 Y0 Z0")
    assert "kept 0 readings" in message and world.position().tilt_deg == 0.0  # never turned
    assert read_rawscan(tmp_path / "offset.jsonl").orientations == []


def test_a_grbl_board_left_in_inches_by_its_startup_block_moves_in_mm(meshes_dir, tmp_path):
    """GRBL runs its startup block (``$N0``) after every reset; one holding ``G20`` (set by a sender for another job)
    makes every move inches. Before: the driver sent only ``G90``, and the first lowering (10 mm, ``G0 Z-10``) went
    to Z -254 mm, 244 mm deeper than commanded (on a real rig, into the tank's floor); the arrival check then stopped
    the scan (exit 3) with advice on work offsets. Now ``G21`` follows ``G90`` at connect (and after homing or
    unlocking), so the moves are in mm whatever the board kept."""
    from rig_helpers import make_world

    inches = make_world(meshes_dir, "inches", grbl_startup="G20")
    raw = scan(inches, "grbl", "level", plan_for(2, step=10.0), tmp_path / "inches.jsonl")
    assert [o.complete for o in raw.orientations] == [True, True]
    clean = make_world(meshes_dir, "mm")
    reference = scan(clean, "grbl", "level", plan_for(2, step=10.0), tmp_path / "mm.jsonl")
    for a, b in zip(raw.orientations, reference.orientations):
        np.testing.assert_allclose(a.values, b.values)

def test_a_dip_whose_readings_never_change_is_not_completed_and_the_resume_redoes_it(meshes_dir, tmp_path):
    """A stuck level sensor (every line ``L=150.000 mm``). Before: all dips recorded complete, exit 0 ("scan
    complete: 8 orientations, 184 readings"), then ``reconstruct.py`` refused the whole file: "profile 0 sums to
    0 mm^3". Now the first such dip stops the scan, kept as an incomplete dip, and the run after the repair dips it."""
    from rig_helpers import make_world

    stuck = make_world(meshes_dir, "stuck", sensor_format={"level_format": "L=150.000 mm"})
    plan, path = plan_for(2, step=10.0), tmp_path / "stuck.jsonl"
    with pytest.raises(ScanAborted, match=r"at the end of orientation 0 \(tilt 41.4096, spin 0\): SensorError: all 11 "
                                          r"readings of orientation 0 are 150 mm, from lower 0 to 100 mm: .* the dip "
                                          r"is not marked complete .*object lifted"):
        scan(stuck, "grbl", "level", plan, path)
    kept = read_rawscan(path)
    assert [(o.k, o.complete, o.n_readings) for o in kept.orientations] == [(0, False, 11)]
    stuck.sensor_format.level_format = "L={value:.3f} mm"  # the sensor repaired
    stuck.reset()
    resumed = scan(stuck, "grbl", "level", plan, path)
    assert [(o.k, o.complete) for o in resumed.orientations] == [(0, True), (1, True)]
    assert np.ptp(resumed.orientations[0].values) > 1.0


def test_a_lost_position_stops_a_scan_into_another_file_on_the_same_rig_too(meshes_dir, tmp_path):
    """A board without homing loses the link while lowering (it may restart and count from 0 where the object is).
    Before: the marker beside scan ``a`` kept ``a`` from moving, but a scan ``b`` on the same rig (a new
    ``name``) made 30 moves, trusting the position, no homing and no confirmation. Now the marker is also kept
    beside the port's lock, for every scan on that port, until a run homes or the operator confirms the position."""
    from dipnet.core.rawscan import ScanHeader
    from dipnet.rig.fake.server import serve
    from dipnet.rig.grbl import GrblController
    from dipnet.rig.runner import ScanRunner
    from dipnet.rig.sensors import LineSensor
    from rig_helpers import AREA, make_world

    world = make_world(meshes_dir, "nohoming", grbl_settings={22: 0})
    world.reset(faults=[{"kind": "disconnect", "at_move": 8}])

    def run(name: str, **options):
        ctl = GrblController(server.urls["grbl"], timeout=0.5, move_timeout=2.0)
        sensor = LineSensor(server.urls["level"], pattern=r"L=(?P<value>[-+\d.]+) mm")
        header = ScanHeader(quantity="level_mm", tank_cross_section_mm2=AREA, step_mm=10.0)
        return ScanRunner(ctl, sensor, plan_for(2, step=10.0), tmp_path / name, header, progress=False, fsync=False,
                          home=None, **options).run()

    with serve(world, ["grbl", "level"]) as server:
        with pytest.raises(ScanAborted, match="OBJECT NOT LIFTED"):
            run("a.jsonl")
        moved = world.motion_count
        with pytest.raises(ScanAborted, match=r"a run of the scan .*a\.jsonl on this rig \(socket://127\.0\.0\.1:\d+\) "
                                              r"lost the position \(lost the link .*nothing had moved.*"
                                              r"confirm_position=true"):
            run("b.jsonl")
        assert world.motion_count == moved
        assert len(run("b.jsonl", confirm_position=True).completed()) == 2  # the operator's word clears it
        assert len(run("c.jsonl").completed()) == 2


def test_an_origin_height_that_is_not_a_number_is_refused_naming_the_option():
    """Before: ``scan.py rig.origin_height_mm=nan`` ended in "error: Out of range float values are not JSON
    compliant", naming no option."""
    with pytest.raises(ValueError, match=r"^rig\.origin_height_mm must be a finite height \(mm\) or null, got nan; "
                                         r"nothing moved$"):
        ScanPlan([(0.0, 0.0)], start_mm=0.0, stop_mm=30.0, step_mm=10.0, origin_height_mm=float("nan"))


@pytest.mark.parametrize("angles", [False, True])
def test_a_file_not_recorded_by_a_rig_scan_is_refused_not_resumed(world, tmp_path, angles):
    """The audit's case: a simulated recording in the scan's place, its header's fields the scan's own. Its dips
    along directions only made the resume fail with "TypeError: unsupported operand type(s) for -: 'NoneType' and
    'float'"; its dips at the plan's rig angles were resumed, the rig's dips appended under the simulation's header."""
    from dipnet.core.rawscan import OrientationScan, RawScan, ScanHeader
    from rig_helpers import AREA

    plan, path = plan_for(3, step=10.0), tmp_path / "scan.jsonl"
    tilt, spin = plan.orientations[0]
    dip = OrientationScan(k=0, direction=None if angles else [0.0, 0.0, 1.0], tilt_deg=tilt if angles else None,
                          spin_deg=spin if angles else None, stage_mm=[0.0, 10.0, 20.0, 30.0],
                          values=[150.0, 151.0, 152.0, 153.0], time_s=[0.0, 1.0, 2.0, 3.0], complete=True)
    header = ScanHeader(tank_cross_section_mm2=AREA, step_mm=plan.step_mm, resolution=0.001, rig="simulator")
    RawScan(header=header, orientations=[dip]).save(path)
    before = path.read_bytes()
    world.reset()
    with pytest.raises(RawScanFileError, match=r"scan.jsonl: cannot resume, the file was not recorded by a rig scan "
                                               r"\(its header records no plan; rig 'simulator'\)"):
        scan(world, "grbl", "level", plan, path)
    assert path.read_bytes() == before and world.max_lower_seen == 0.0


@pytest.mark.parametrize("text", ['{"reason": "ALARM:1 hard li', "", "[]"])
def test_a_position_lost_marker_cut_short_still_stops_the_scan_and_homing_clears_it(world, tmp_path, text):
    """A marker cut short (a run killed while it wrote it: the write truncated the file first), emptied or edited.
    Before: every resume stopped with "JSONDecodeError: Unterminated string ..." (or "AttributeError: 'list' object
    has no attribute 'get'"), naming no file, and so did ``home=true``, the remedy its message gave: the scan could
    not go on until the marker was found and deleted by hand. Now the unreadable marker still says that the position
    was lost, naming it: nothing moves without homing or confirmation, and homing clears it."""
    plan, path = plan_for(2, step=10.0), tmp_path / "scan.jsonl"
    marker = path.with_name(path.name + ".position-lost.json")
    marker.write_text(text)
    world.reset()
    with pytest.raises(ScanAborted, match=r"the previous run lost the position \(unknown: its marker .*"
                                          r"position-lost\.json (cannot be read|holds no record).*nothing had moved"):
        scan(world, "grbl", "level", plan, path, home=False)
    assert world.motion_count == 0
    raw = scan(world, "grbl", "level", plan, path, home=True)
    assert len(raw.completed()) == 2 and not marker.exists()
