"""The scan job's plan settings: one rig geometry (values or a calibration file), the deepest lowering."""

import pytest
from hydra import compose, initialize_config_module

from dipnet.core.calibration_file import Calibration, save_calibration
from dipnet.core.geometry import RigGeometry
from dipnet.core.rawscan import read_rawscan
from dipnet.jobs.deprecations import upgrade_scan_config
from dipnet.jobs.scan import deepest_lowering, plan_settings, scan_geometry

from rig_helpers import make_world


def _scan_cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return upgrade_scan_config(compose(config_name="scan", overrides=list(overrides)))


def test_the_rig_geometry_node_is_the_plans_geometry():
    cfg = _scan_cfg("rig=grbl", "rig.geometry.pivot_mm=12", "rig.origin_height_mm=40")
    settings = plan_settings(cfg)
    assert settings["geometry"] == RigGeometry(pivot_mm=12.0) and settings["origin_height_mm"] == 40
    assert settings["step_mm"] == cfg.protocol.step_mm and settings["max_lower_mm"] is None


def test_a_calibration_file_gives_the_geometry_but_not_beside_values(tmp_path):
    path = save_calibration(Calibration(RigGeometry(pivot_mm=7.0), rig="grbl-rig", tank="t"), tmp_path / "c.yaml")
    assert scan_geometry(_scan_cfg("rig=grbl", f"+rig.calibration={path}").rig) == RigGeometry(pivot_mm=7.0)
    with pytest.raises(ValueError, match="either as a calibration file .* or as values"):
        scan_geometry(_scan_cfg("rig=grbl", f"+rig.calibration={path}", "rig.geometry.pivot_mm=3").rig)


def test_the_deepest_lowering_is_the_configured_one():
    assert deepest_lowering(_scan_cfg("rig=grbl", "rig.max_lower_mm=80")) == {"max_lower_mm": 80.0,
                                                                                "max_lower_source": "rig.max_lower_mm"}


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
