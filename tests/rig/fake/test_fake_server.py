"""The fake rig's socket server (dipnet.rig.fake.server): a scan over TCP equals the same scan in-process."""

from __future__ import annotations

import numpy as np

from dipnet.core.rawscan import ScanHeader
from dipnet.rig.fake.server import serve
from dipnet.rig.grbl import GrblController
from dipnet.rig.runner import ScanRunner
from dipnet.rig.sensors import LineSensor

from rig_helpers import AREA, plan_for, scan


def test_socket_server_mode(world, tmp_path):
    world.reset()
    reference = scan(world, "grbl", "level", plan_for(2, step=10.0), tmp_path / "local.jsonl")
    world.reset()
    with serve(world, ["grbl", "level"]) as server:
        assert server.urls["grbl"].startswith("socket://127.0.0.1:")
        ctl = GrblController(server.urls["grbl"], timeout=1.0)
        sensor = LineSensor(server.urls["level"], pattern=r"L=(?P<value>[-+\d.]+) mm")
        plan = plan_for(2, step=10.0)
        header = ScanHeader(quantity="level_mm", tank_cross_section_mm2=AREA, step_mm=10.0)
        raw = ScanRunner(ctl, sensor, plan, tmp_path / "remote.jsonl", header, progress=False, fsync=False).run()
    assert len(raw.completed()) == 2
    for a, b in zip(reference.orientations, raw.orientations):
        assert np.allclose(a.values, b.values) and np.allclose(a.stage_mm, b.stage_mm)
