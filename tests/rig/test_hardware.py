"""Smoke tests on a real rig (skipped unless ``pytest --run-hardware``).

Set ``DIPNET_CONTROLLER_URL`` (and ``DIPNET_DIALECT=grbl|marlin``) and ``DIPNET_SENSOR_URL``
(a level sensor printing numbers in mm). Nothing is lowered: the axes stay where they are.
"""

from __future__ import annotations

import math
import os

import pytest

from dipnet.rig.grbl import GrblController
from dipnet.rig.marlin import MarlinController
from dipnet.rig.sensors import LineSensor


def _env(name: str) -> str:
    value = os.environ.get(name)
    if not value:
        pytest.skip(f"set {name} to run this hardware test")
    return value


@pytest.mark.hardware
def test_controller_reports_its_position():
    cls = MarlinController if os.environ.get("DIPNET_DIALECT", "grbl") == "marlin" else GrblController
    ctl = cls(_env("DIPNET_CONTROLLER_URL"))
    ctl.connect()
    try:
        pos = ctl.position()
        assert all(math.isfinite(v) for v in (pos.lower_mm, pos.tilt_deg, pos.spin_deg))
    finally:
        ctl.close()


@pytest.mark.hardware
def test_level_sensor_reads_millimetres():
    sensor = LineSensor(_env("DIPNET_SENSOR_URL"))
    sensor.connect()
    try:
        value, unit, _ = sensor.read()
        assert unit == "mm" and math.isfinite(value)
    finally:
        sensor.close()
