"""Talking bytes to one fake device directly (no driver, no port), for the tests of tests/rig/fake."""

from __future__ import annotations

from dipnet.rig.fake.device import Device
from dipnet.rig.fake.world import FakeRig
from dipnet.shapes import Ball
from dipnet.simulator.physics import Tank


def ball_world(**options) -> FakeRig:
    """A fake rig holding a ball of radius 20 mm in a 20,000 mm^2 tank, instant moves unless ``move_s`` is given."""
    return FakeRig(Ball(20.0), tank=Tank(cross_section_mm2=20000.0), origin_height_mm=30.0, **options)


def replies(device: Device, data: bytes | str = b"", timeout: float = 0.05) -> list[str]:
    """Send ``data`` (a str gets a newline) and collect the reply lines until none comes for ``timeout`` s."""
    if data:
        device.receive(data if isinstance(data, bytes) else data.encode("ascii") + b"\n")
    out = b""
    while chunk := device.take(4096, timeout):
        out += chunk
    return [line.strip() for line in out.decode("ascii").splitlines() if line.strip()]
