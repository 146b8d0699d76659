"""A fake-rig scan names its shape in its header: reconstructing it is scored against that shape."""

from __future__ import annotations

import json
import math

import pytest
from functools import partial

from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.jobs.pipeline import run
from dipnet.jobs.scan import scan_from_config
from dipnet.preprocessing.sources import RecordedSource, read_recorded
from dipnet.preprocessing.truth import recorded_shape_spec


def _compose(name, overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


def test_fake_rig_scan_is_scored_against_its_shape(tmp_path):
    scan_cfg = _compose("scan", ["n_dips=24", "protocol.step_mm=4", "fsync=false", "progress=false",
                                 "rig.fake.shape.name=ball", "rig.fake.shape.radius=30"])
    path = tmp_path / "rawscan.jsonl"
    scan_from_config(scan_cfg, path)
    shape = RecordedSource(partial(read_recorded, path=path)).truth(build=instantiate)
    assert shape.name == "ball" and abs(shape.radius() - 30.0) < 1e-6

    result = run(_compose("config", ["source=recorded", f"source.reader.path={path}", "resolution=20",
                                     "output.progress=false", "output.figures=false"]), tmp_path / "job")
    saved = json.loads((tmp_path / "job" / "metrics.json").read_text())
    assert saved["shape"] == "ball" and saved["iou"] == result.metrics["iou"] >= 0.75
    exact = 4 / 3 * math.pi * 30.0**3  # the scan measured this ball in mm, and is scored against it
    assert saved["measured_volume_mm3"] == pytest.approx(exact, rel=0.02)
    assert saved["volume_error"] == pytest.approx(saved["reconstructed_volume_mm3"] / exact - 1, rel=1e-6)


def test_files_without_a_named_shape_give_none(tmp_path):
    (tmp_path / "m.npz").write_bytes(b"")
    assert recorded_shape_spec(tmp_path / "m.npz") is None
