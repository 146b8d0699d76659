"""The scan job's plan settings: one rig geometry (values or a calibration file), the deepest lowering."""

import pytest
from hydra import compose, initialize_config_module

from dipnet.core.calibration_file import Calibration, save_calibration
from dipnet.core.geometry import RigGeometry
from dipnet.jobs.deprecations import upgrade_scan_config
from dipnet.jobs.scan import deepest_lowering, plan_settings, scan_geometry


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
