"""Old config spellings still read, with a warning naming the new one."""

import pytest
from hydra import compose, initialize_config_module

from dipnet.jobs.deprecations import ConfigDeprecation, upgrade_config, upgrade_scan_config


def _compose(name, *overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def test_the_readers_symmetry_moves_to_the_top_level():
    cfg = _compose("config", "source=recorded", "source.reader.path=x.npz", "+source.reader.symmetry={n_fold: 3}")
    with pytest.warns(ConfigDeprecation, match=r"source.reader.symmetry is deprecated: use symmetry=\{n_fold: 3\}"):
        upgraded = upgrade_config(cfg)
    assert upgraded.symmetry == {"n_fold": 3} and "symmetry" not in upgraded.source.reader
    assert cfg.source.reader.symmetry == {"n_fold": 3}  # the job's config is left as it was


def test_a_given_old_spelling_replaces_the_new_and_the_new_spelling_is_silent(recwarn):
    cfg = _compose("config", "source=recorded", "source.reader.path=x.npz", "+source.reader.symmetry={n_fold: 3}",
                   "symmetry={n_fold: 2}")
    with pytest.warns(ConfigDeprecation):
        assert upgrade_config(cfg).symmetry == {"n_fold": 3}
    recwarn.clear()
    upgrade_config(_compose("config", "symmetry={n_fold: 2}"))
    assert not [w for w in recwarn if issubclass(w.category, ConfigDeprecation)]


def test_the_origin_height_leaves_the_rig_geometry():
    with pytest.warns(ConfigDeprecation,
                      match="rig.geometry.origin_height_mm is deprecated: use rig.origin_height_mm=60"):
        upgraded = upgrade_scan_config(_compose("scan", "rig=grbl", "rig.geometry.origin_height_mm=60"))
    assert upgraded.rig.origin_height_mm == 60 and "origin_height_mm" not in upgraded.rig.geometry


def test_the_rig_geometry_is_one_node_in_every_config():
    fields = {"pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale", "cross_section_mm2",
              "level_drift_mm_per_s", "sensor_lag_s"}
    nodes = [_compose("config").source.simulator.geometry,
             _compose("config", "experiment=cats_real").source.reader.geometry,
             upgrade_scan_config(_compose("scan")).rig.geometry]
    for node in nodes:
        assert node._target_ == "dipnet.core.geometry.RigGeometry" and set(node) - {"_target_"} == fields
    assert nodes[1].pivot_mm == 188.0


def test_an_orientations_node_in_a_scan_config_becomes_the_sets_name_and_top_level_keys():
    from omegaconf import OmegaConf

    old = OmegaConf.merge(_compose("scan"), {"orientations": {"kind": "grid", "tilts": [0, 30], "spins": [0, 180],
                                                               "max_tilt_deg": 45.0}})
    with pytest.warns(ConfigDeprecation, match="orientations.kind is deprecated: use orientations=grid"):
        upgraded = upgrade_scan_config(old)
    assert upgraded.orientations == "grid" and list(upgraded.tilts) == [0, 30] and list(upgraded.spins) == [0, 180]
    assert upgraded.max_tilt_deg == 45.0


def test_orientations_mean_the_same_in_the_scan_and_the_reconstruct_config(recwarn):
    from dipnet.jobs.scan import orientations_from_config

    scan, reconstruct = _compose("scan", "n_dips=12"), _compose("config", "n_dips=12")
    assert scan.orientations == reconstruct.orientations == "fibonacci"
    assert len(orientations_from_config(upgrade_scan_config(scan))) == 12
    grid = upgrade_scan_config(_compose("scan", "orientations=grid", "tilts=[0,25]", "spins=[0,180]",
                                        "max_tilt_deg=30"))
    assert orientations_from_config(grid) == [(0.0, 0.0), (0.0, 180.0), (25.0, 0.0), (25.0, 180.0)]
    beyond = upgrade_scan_config(_compose("scan", "orientations=grid", "tilts=[0,25,50]", "spins=[0,180]",
                                          "max_tilt_deg=30"))
    with pytest.raises(ValueError, match="50 deg outside the rig's tilt range"):  # refused, no longer dropped
        orientations_from_config(beyond)
    assert not [w for w in recwarn if issubclass(w.category, ConfigDeprecation)]
