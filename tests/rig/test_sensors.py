"""Sensor drivers (dipnet.rig.sensors): balance and level-line parsers, Modbus registers and frames, a Modbus
level sensor against the fake rig's slave."""

from __future__ import annotations

import pytest

from dipnet.rig import sensors
from dipnet.rig.controller import RigTimeout
from dipnet.rig.sensors import ModbusLevelSensor, SensorError


def test_balance_lines():
    assert sensors.parse_ad("ST,+00123.45  g") == (123.45, "g", True)
    assert sensors.parse_ad("US,-00001.20  g") == (-1.2, "g", False)
    assert sensors.parse_ad("ST,+0001.234 kg") == pytest.approx((1234.0, "g", True))
    with pytest.raises(sensors.SensorError, match="overload"):
        sensors.parse_ad("OL,+9999999E+19")
    with pytest.raises(sensors.SensorError, match="counting"):
        sensors.parse_ad("QT,+00012345 PC")
    assert sensors.parse_sics("S S     100.00 g") == (100.0, "g", True)
    assert sensors.parse_sics("S D     100.01 g") == (100.01, "g", False)
    assert sensors.parse_sics("S S       0.250 kg") == (250.0, "g", True)
    busy = sensors.parse_sics("S I")
    assert not busy.stable and busy.value != busy.value  # NaN: no value yet
    for bad, word in (("S +", "overload"), ("S -", "underload"), ("ES", "syntax"), ("EL", "logical")):
        with pytest.raises(sensors.SensorError, match=word):
            sensors.parse_sics(bad)


def test_level_line_pattern():
    pattern = r"LVL\s*(?P<value>[-+]?\d+\.\d+)\s*(?P<unit>mm)(?P<flag>\?)?"
    assert sensors.parse_line("LVL 151.234 mm", pattern) == (151.234, "mm", True)
    assert sensors.parse_line("LVL 151.234 mm?", pattern) == (151.234, "mm", False)
    assert sensors.parse_line("garbage", pattern) is None


def test_modbus_frames_and_registers():
    from dipnet.rig.fake.sensors import crc16, with_crc

    assert crc16(b"123456789") == 0x4B37  # the CRC-16/MODBUS check value
    assert with_crc(bytes.fromhex("010300000001")).hex() == "010300000001840a"  # a textbook request
    assert crc16(with_crc(b"\x01\x03\x04\x00\x02\x4f\x6c")) == 0
    assert sensors.decode_registers([0x0002, 0x4F6C], "int32", "big") == 151404
    assert sensors.decode_registers([0x4F6C, 0x0002], "int32", "little") == 151404
    for dtype in ("int16", "uint16", "int32", "uint32", "float32"):
        for order in ("big", "little"):
            value = -123.0 if dtype.startswith("int") or dtype == "float32" else 4567.0
            regs = sensors.encode_registers(value, dtype, order)
            assert sensors.decode_registers(regs, dtype, order) == pytest.approx(value)


def test_modbus_sensor_reads_real_frames_and_reports_faults(world):
    world.reset()
    good = ModbusLevelSensor(world.url("modbus"), data_type="int32", scale=0.001, timeout=0.2)
    good.connect()
    assert good.read().value == pytest.approx(world.tank.rest_level_mm, abs=1e-3)
    good.close()
    wrong_register = ModbusLevelSensor(world.url("modbus"), address=7, timeout=0.2)  # exception 2 from the slave
    wrong_register.connect()
    with pytest.raises(SensorError, match="IllegalRequestError"):
        wrong_register.read()
    wrong_register.close()
    wrong_slave = ModbusLevelSensor(world.url("modbus"), slave=9, timeout=0.1)  # a real slave stays silent
    wrong_slave.connect()
    with pytest.raises(RigTimeout):
        wrong_slave.read()
    wrong_slave.close()
