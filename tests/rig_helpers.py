"""Helpers shared by the rig tests (tests/rig, tests/rig/fake, tests/jobs/test_scan.py): a fake world with a torus,
scans through the real drivers."""

from __future__ import annotations

from dipnet.core.rawscan import ScanHeader
from dipnet.rig.fake.world import FakeRig
from dipnet.rig.grbl import GrblController
from dipnet.rig.marlin import MarlinController
from dipnet.rig.runner import ScanPlan, ScanRunner, plan_orientations
from dipnet.rig.sensors import AveragingSensor, BalanceSensor, LineSensor, ModbusLevelSensor
from dipnet.simulator.physics import Tank

AREA = 20000.0  # tank cross-section (mm^2): a 200 x 100 mm tank
ORIGIN = 50.0   # object origin above the water at lower_mm = 0 (mm)
CONTROLLERS = {"grbl": GrblController, "marlin": MarlinController}


def make_world(meshes_dir, name: str, **options) -> FakeRig:
    """A registered fake world holding the bundled torus (radius 42 mm)."""
    from dipnet.shapes import load_mesh

    shape = load_mesh(meshes_dir / "torus.ply", radius=42.0)
    return FakeRig(shape, tank=Tank(cross_section_mm2=AREA), origin_height_mm=ORIGIN, **options).register(name)


def make_sensor(world: FakeRig, kind: str):
    url = world.url(kind)
    if kind == "level":
        return AveragingSensor(LineSensor(url, pattern=r"L=(?P<value>[-+\d.]+)\s*(?P<unit>mm)"), n=3, max_spread=0.05)
    if kind == "modbus":
        return AveragingSensor(ModbusLevelSensor(url, data_type="int32", scale=0.001, baudrate=115200), n=2,
                               max_spread=0.05)
    return BalanceSensor(url, style=kind)


def make_runner(world, dialect, sensor, plan, path, move_timeout: float = 2.0, axes=None, **options) -> ScanRunner:
    """A scan runner on ``world`` through the real driver of ``dialect`` (``axes``: its axis mapping, as the
    world's for a world with other axes)."""
    ctl = CONTROLLERS[dialect](world.url(dialect), axes, timeout=0.3, move_timeout=move_timeout)
    sensor = sensor if not isinstance(sensor, str) else make_sensor(world, sensor)
    header = ScanHeader(quantity=sensor.quantity, tank_cross_section_mm2=AREA, step_mm=plan.step_mm,
                        resolution=0.001, rig=f"fake-{dialect}")
    return ScanRunner(ctl, sensor, plan, path, header, progress=False, fsync=False, **options)


def scan(world, dialect, sensor, plan, path, **options):
    """Run (or resume) a scan of ``world`` with the real driver of ``dialect``."""
    return make_runner(world, dialect, sensor, plan, path, **options).run()


def plan_for(k: int, step: float = 3.0) -> ScanPlan:
    return ScanPlan(plan_orientations("fibonacci", k), start_mm=0.0, stop_mm=100.0, step_mm=step, safe_mm=0.0,
                    origin_height_mm=ORIGIN)
