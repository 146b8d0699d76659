"""The scan job: a rig, sensor and plan built from a scan config (``conf/scan.yaml``), run or resumed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dipnet.core.calibration_file import TANK_CONFIG_KEY, Calibration, load_calibration
from dipnet.core.geometry import RigGeometry, as_geometry
from dipnet.core.counts import whole_number
from dipnet.core.grid import Grid
from dipnet.core.orientations import Reach
from dipnet.core.rawscan import RawScan, ScanHeader, read_rawscan
from dipnet.jobs.deprecations import upgrade_scan_config
from dipnet.jobs.options import ConfigError, instantiates
from dipnet.planning.plans import AdaptivePlan
from dipnet.rig.adaptive import adaptive_scan
from dipnet.rig.controller import Controller
from dipnet.rig.runner import ScanPlan, ScanRunner, plan_orientations, tilt_reach
from dipnet.rig.sensors import AveragingSensor


def build_header(cfg: dict[str, Any], controller: Controller, sensor, plan: ScanPlan) -> ScanHeader:
    """The raw scan header from the scan config (the runner adds the rig identity); ``rig.tank``, when
    given, is recorded as the scan's tank (``config["tank_id"]``), which calibration files are checked against."""
    rig = cfg.get("rig", {})
    tank = {TANK_CONFIG_KEY: str(rig["tank"])} if rig.get("tank") is not None else {}
    return ScanHeader(
        quantity=sensor.quantity, ndim=3, tank_cross_section_mm2=rig.get("tank_cross_section_mm2"),
        step_mm=float(plan.step_mm), resolution=rig.get("resolution"),
        rig=str(rig.get("name", controller.dialect)),
        config={"scan": cfg, **tank},
        metadata=dict(cfg.get("metadata") or {}))


def scan_from_config(cfg, path: str | Path, progress: bool | None = None, journal=None) -> RawScan:
    """Build the rig from a scan config (``conf/scan.yaml``) and run (or resume) the scan.

    ``cfg.rig`` holds ``controller`` (``_target_``), ``sensor_url``, ``tank_cross_section_mm2``,
    ``geometry`` and optionally ``fake`` (a :class:`~dipnet.rig.fake.world.FakeRig`, registered under its
    name so the ``fakerig://`` URLs reach it); ``cfg.sensor`` holds ``device`` (``_target_``) and
    ``average``; ``cfg.protocol`` and the orientations (:func:`orientations_from_config`) the plan.
    ``journal``: a :class:`~dipnet.monitor.journal.MonitorJournal` sampling the runner (``monitor=true``).
    """

    cfg = upgrade_scan_config(cfg)
    world = register_fake_rig(cfg)
    plan = ScanPlan(orientations_from_config(cfg), **plan_settings(cfg, world))
    return runner_from_config(cfg, plan, path, progress=progress, journal=journal).run()


def orientations_from_config(cfg) -> list[tuple[float, float]]:
    """The ``(tilt_deg, spin_deg)`` pairs of a scan config: ``cfg.orientations`` names the set (as in
    ``conf/config.yaml``), with ``n_dips`` and ``seed`` (fibonacci, random) or ``tilts`` x ``spins`` (grid),
    within ``max_tilt_deg``."""
    from omegaconf import OmegaConf

    def angles(key: str):
        value = cfg.get(key)
        return None if value is None else OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) \
            else value

    # n_dips=1.5 scanned 1 dip and seed=1.5 used seed 1, without a word; seed=abc was "invalid literal for int()"
    return plan_orientations(str(cfg.orientations), n=whole_number("n_dips", cfg.n_dips, 1), tilts=angles("tilts"),
                             spins=angles("spins"), seed=whole_number("seed", cfg.seed, 0),
                             max_tilt_deg=float(cfg.max_tilt_deg))


def register_fake_rig(cfg):
    """Register ``cfg.rig.fake`` (a :class:`~dipnet.rig.fake.world.FakeRig`) so its ``fakerig://`` URLs
    resolve; returns it (``None`` for a real rig)."""
    from hydra.utils import instantiate

    if cfg.rig.get("fake") is None:
        return None
    return instantiate(cfg.rig.fake, _convert_="all").register()


def plan_settings(cfg, world=None) -> dict[str, Any]:
    """The :class:`ScanPlan` keyword arguments of a scan config besides the orientations:
    ``cfg.protocol``, ``cfg.rig.origin_height_mm``, the rig geometry (``cfg.rig.geometry``, a
    :class:`~dipnet.core.geometry.RigGeometry` node, or the calibration file ``cfg.rig.calibration``:
    not both) and the deepest lowering: ``cfg.rig.max_lower_mm`` or, shallower, the tank bottom of the
    fake rig ``world``."""
    from omegaconf import OmegaConf

    return {**OmegaConf.to_container(cfg.protocol, resolve=True), "origin_height_mm": cfg.rig.get("origin_height_mm"),
            "geometry": scan_geometry(cfg.rig), **deepest_lowering(cfg, world)}


def scan_geometry(rig_cfg) -> RigGeometry:
    """The geometry the scan assumes: ``rig.calibration``'s (a file) or ``rig.geometry``'s (values), the
    ideal rig without either; both given (values not ideal) is an error."""
    from hydra.utils import instantiate

    node = rig_cfg.get("geometry")
    configured = as_geometry(instantiate(node) if node is not None and "_target_" in node else node)
    calibration = rig_calibration(rig_cfg)
    if calibration is None:
        return configured
    if configured != RigGeometry():
        raise ValueError("give the rig geometry either as a calibration file (rig.calibration) or as values "
                         "(rig.geometry), not both")
    return calibration.geometry


def deepest_lowering(cfg, world=None) -> dict[str, Any]:
    """``max_lower_mm`` and where it comes from: ``cfg.rig.max_lower_mm`` or the fake rig's tank bottom."""
    limits = [] if cfg.rig.get("max_lower_mm") is None else [(float(cfg.rig.max_lower_mm), "rig.max_lower_mm")]
    if world is not None:
        limits.append((world.deepest_lower_mm(float(cfg.get("max_tilt_deg", 90.0))),
                       f"the fake rig's tank holds {world.tank.rest_level_mm:g} mm of water, the object's radius is "
                       f"{world.shape.radius():.4g} mm"))
    deepest = min(limits, default=(None, "rig.max_lower_mm"))
    return {"max_lower_mm": deepest[0], "max_lower_source": deepest[1]}


def runner_from_config(cfg, plan: ScanPlan, path: str | Path, *, home: bool = True,
                       progress: bool | None = None, journal=None) -> "ScanRunner":
    """A :class:`ScanRunner` for ``plan`` on the controller and sensor of a scan config, its header
    recording the config and the rig calibration. ``home=False`` never homes (a later batch of an
    adaptive scan); otherwise ``cfg.home`` decides (null: home when the board can). A ``journal``
    (:class:`~dipnet.monitor.journal.MonitorJournal`) samples the runner's state from then on."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    for option, url in (("rig.controller.url", cfg.rig.controller.get("url")),
                        ("rig.sensor_url", cfg.rig.get("sensor_url"))):
        if isinstance(url, str) and not url.strip():  # was "RigDisconnected: cannot open : ...", exit 3
            raise ConfigError(f"{option} is empty ({url!r}): give the port's pyserial URL (/dev/ttyUSB0, COM3, "
                              "socket://host:port, fakerig://...); nothing moved")
    controller = instantiate(cfg.rig.controller, _convert_="all")
    device = instantiate(cfg.sensor.device, _convert_="all")
    sensor = AveragingSensor(device, **OmegaConf.to_container(cfg.sensor.average, resolve=True))
    header = build_header(OmegaConf.to_container(cfg, resolve=True), controller, sensor, plan)
    calibration = rig_calibration(cfg.rig)
    if calibration is not None:
        header.config.update({TANK_CONFIG_KEY: calibration.tank, "calibration": calibration.to_dict()})
        header.tank_cross_section_mm2 = calibration.geometry.area(header.tank_cross_section_mm2)
    configured = cfg.get("home")
    runner = ScanRunner(controller, sensor, plan, path, header,
                        home=(None if configured is None else bool(configured)) if home else False,
                        progress=bool(cfg.progress if progress is None else progress), fsync=bool(cfg.fsync),
                        rehome_on_fault=bool(cfg.get("rehome_on_fault", False)),
                        confirm_position=bool(cfg.get("confirm_position", False)))
    if journal is not None:
        journal.watch(runner)
    return runner


def rig_calibration(rig_cfg) -> Calibration | None:
    """The calibration file named by ``rig.calibration`` (checked against ``rig.name`` and ``rig.tank``)."""
    path = rig_cfg.get("calibration")
    if not path:
        return None
    return load_calibration(path, rig=str(rig_cfg.get("name")), tank=rig_cfg.get("tank"))


def adaptive_scan_from_config(cfg, path: str | Path, journal=None) -> RawScan:
    """``scripts/scan.py +planner=adaptive [+reach=authors_rig]``: the rig, sensor and dip protocol of the
    scan config (as :func:`~dipnet.jobs.scan.scan_from_config`), the loop of ``cfg.planner`` (an
    :class:`~dipnet.planning.plans.AdaptivePlan`) and the reach of :func:`adaptive_reach` (within ``max_tilt_deg``);
    reconstructions with the ``voxel`` solver on a ``cfg.planner.resolution`` grid (default 32) of side
    ``cfg.planner.extent_mm`` (default 100 mm): with ``minnorm`` estimates the planner's noise level (their
    misfit) is model error far above the sensor noise and its scores hardly tell candidates apart (see
    :mod:`dipnet.planning.planner`). Returns the raw scan."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from dipnet.solvers.voxel import VoxelSolver

    cfg = upgrade_scan_config(cfg)
    scan_settings = plan_settings(cfg, register_fake_rig(cfg))
    node = OmegaConf.to_container(cfg.planner, resolve=True)
    grid = Grid(int(node.pop("resolution", 32)), 3, float(node.pop("extent_mm", 100.0)))  # the scan's own keys
    plan: AdaptivePlan = instantiate(node)

    def make_runner(plan: ScanPlan, home: bool) -> ScanRunner:
        return runner_from_config(cfg, plan, path, home=home, journal=journal)

    adaptive_scan(make_runner, scan_settings, path, grid, VoxelSolver(progress=False), plan.planner,
                  adaptive_reach(cfg), plan.settings)
    return read_rawscan(path)


def adaptive_reach(cfg) -> Reach:
    """The reach an adaptive scan plans in: ``cfg.reach`` (e.g. ``+reach=authors_rig``), by default the hemisphere up to
    the rig's mechanical tilt limit ``cfg.max_tilt_deg`` (degrees).

    Raises:
        ConfigError: ``cfg.reach`` tilts beyond ``max_tilt_deg`` (the message names both options; nothing moved).
    """
    from hydra.utils import instantiate

    limit = tilt_reach(float(cfg.get("max_tilt_deg", 90.0)))
    if cfg.get("reach") is None:
        return limit
    reach, max_tilt = instantiate(cfg.reach), limit.tilt_range_deg[1]
    if reach.tilt_range_deg[1] > max_tilt:
        raise ConfigError(f"reach.tilt_range_deg={list(reach.tilt_range_deg)} plans tilts beyond max_tilt_deg="
                         f"{max_tilt:g} (the rig's mechanical limit): give reach.tilt_range_deg=[0,{max_tilt:g}] or a "
                         "larger max_tilt_deg; nothing moved")
    return reach


def scan_job(cfg, path: str | Path, journal=None) -> RawScan:
    """The scan of ``scripts/scan.py``: planned dip by dip when ``cfg.planner`` is an adaptive plan
    (:func:`adaptive_scan_from_config`), else up front from the orientations of the config (:func:`scan_from_config`).
    ``journal``: the monitor's (``monitor=true``), sampling the runner."""
    if cfg.get("planner") is not None and instantiates(cfg, "planner", AdaptivePlan):
        return adaptive_scan_from_config(cfg, path, journal=journal)
    return scan_from_config(cfg, path, journal=journal)
