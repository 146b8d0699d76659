"""The ``fakerig://<world>/<device>`` URL handler (dipnet.rig.protocol_fakerig): pyserial opens a port wired to a
registered fake world's device; bad URLs, closed ports and dead links are named errors."""

from __future__ import annotations

import pytest
import serial
from serial.serialutil import PortNotOpenError, SerialException

from dipnet.rig import register_url_handlers
from dipnet.rig.fake.world import FakeRig
from dipnet.shapes import Ball


@pytest.fixture(scope="module")
def ball_rig() -> FakeRig:
    register_url_handlers()
    return FakeRig(Ball(20.0), grbl_settings={22: 0}).register("urlrig")


def test_a_port_talks_to_the_registered_world(ball_rig):
    port = serial.serial_for_url("fakerig://urlrig/grbl", timeout=0.2)
    assert port.is_open and type(port).__module__ == "dipnet.rig.protocol_fakerig"
    assert port.readline().strip() == b"" and port.readline().strip() == b"Grbl 1.1h ['$' for help]"
    port.write(b"$I\n")
    assert [port.readline().strip() for _ in range(3)] == [b"[VER:1.1h.20190830:]", b"[OPT:V,15,128]", b"ok"]
    assert port.in_waiting == 0 and port.read(10) == b""  # nothing more: the timeout, no bytes
    port.write(b"?")
    assert port.readline().startswith(b"<Idle|MPos:")
    with pytest.raises(SerialException, match="already open"):
        port.open()
    port.close()
    with pytest.raises(PortNotOpenError):
        port.read(1)


@pytest.mark.parametrize("url,message", [
    ("fakerig://urlrig", "expected fakerig://<world>/<device>"),
    ("fakerig://nowhere/grbl", "no fake rig named 'nowhere' is registered"),
    ("fakerig://urlrig/toaster", "unknown fake device 'toaster'"),
])
def test_bad_urls_are_named(ball_rig, url, message):
    with pytest.raises(SerialException, match=message):
        serial.serial_for_url(url)


def test_a_dead_link_says_the_device_disconnected(ball_rig):
    port = serial.serial_for_url("fakerig://urlrig/level", timeout=0.2)
    assert port.readline().startswith(b"L=")
    port.device.dead = True  # what a 'disconnect' fault does
    with pytest.raises(SerialException, match="fakerig://urlrig/level: device disconnected"):
        port.read(1)
    port.close()
