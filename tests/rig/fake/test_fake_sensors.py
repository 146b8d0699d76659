"""The fake sensors (dipnet.rig.fake.sensors): the ASCII level stream and its query mode, the Modbus RTU slave
(CRCs, exceptions, silence), the A&D and MT-SICS balances, each read back with the drivers' parsers."""

from __future__ import annotations

import struct

import pytest

from dipnet.rig import sensors
from dipnet.rig.fake.sensors import BalanceDevice, LevelDevice, ModbusDevice, SicsDevice, crc16, with_crc

from fake_talk import ball_world, replies

PATTERN = r"L=(?P<value>[-+\d.]+)\s*(?P<unit>mm)"


def test_the_level_sensor_streams_the_rest_level_until_the_object_dips():
    world = ball_world()
    dev = LevelDevice(world)
    first = [dev.take(64, 0.1) for _ in range(3)]
    readings = [sensors.parse_line(line.decode().strip(), PATTERN) for line in first]
    assert readings == [(pytest.approx(world.tank.rest_level_mm), "mm", True)] * 3
    world.start_move({"lower_mm": 60.0, "tilt_deg": 0.0, "spin_deg": 0.0})  # 30 mm below the origin: half the ball
    dev.clear_output()
    value, _, _ = sensors.parse_line(dev.take(64, 0.1).decode().strip(), PATTERN)
    assert value - world.tank.rest_level_mm == pytest.approx(world.rise_mm(), abs=1e-3) and world.rise_mm() > 0.1


def test_a_level_sensor_with_a_query_answers_only_when_asked():
    world = ball_world(sensor_format={"level_query": "R\\r", "level_format": "LVL {value:.2f}"})
    dev = LevelDevice(world)
    assert dev.take(64, 0.05) == b""
    assert replies(dev, b"R\r") == [f"LVL {world.tank.rest_level_mm:.2f}"]


def _request(slave: int = 1, function: int = 3, address: int = 0, count: int = 2) -> bytes:
    return with_crc(struct.pack(">BBHH", slave, function, address, count))


def test_the_modbus_slave_answers_a_register_read_with_a_valid_frame():
    world = ball_world()
    dev = ModbusDevice(world)
    dev.receive(_request())
    frame = dev.take(64, 0.1)
    assert crc16(frame) == 0 and frame[:3] == bytes([1, 3, 4])
    regs = struct.unpack(">2H", frame[3:7])
    assert sensors.decode_registers(list(regs), "int32", "big") * 0.001 == pytest.approx(world.tank.rest_level_mm)


@pytest.mark.parametrize("request_frame,reply", [
    (_request(function=4), bytes([1, 0x84, 1])),   # illegal function
    (_request(address=7), bytes([1, 0x83, 2])),    # illegal data address
    (_request(count=1), bytes([1, 0x83, 2])),      # int32 needs two registers
    (_request(slave=9), None),                     # another slave's frame: silence
    (_request()[:-1] + b"\x00", None),             # a corrupted CRC: silence
])
def test_the_modbus_slave_refuses_or_ignores_what_a_real_one_would(request_frame, reply):
    dev = ModbusDevice(ball_world())
    dev.receive(request_frame)
    assert dev.take(64, 0.05) == (b"" if reply is None else with_crc(reply))


def test_the_balances_weigh_the_displaced_water_in_their_own_dialects():
    world = ball_world()
    world.start_move({"lower_mm": 60.0, "tilt_deg": 0.0, "spin_deg": 0.0})
    mass = world.density * world.tank.cross_section_mm2 * world.rise_mm()  # g
    (ad,) = replies(BalanceDevice(world), "Q")
    assert sensors.parse_ad(ad) == (pytest.approx(mass, abs=2e-3), "g", True)
    assert replies(BalanceDevice(world), "XYZ") == ["EC,E01"]
    (sics,) = replies(SicsDevice(world), "SI")
    assert sensors.parse_sics(sics) == (pytest.approx(mass, abs=2e-3), "g", True)
    assert replies(SicsDevice(world), "Q") == ["ES"]
