"""Sensor drivers (dipnet.rig.sensors): balance and level-line parsers, Modbus registers and frames, a Modbus
level sensor against the fake rig's slave."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

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
    with pytest.raises(SensorError, match="'garbage'"):
        sensors.parse_line("garbage", pattern)


@pytest.mark.parametrize("line,value", [
    ("151.234 mm", 151.234), ("  151.234 mm\r", 151.234), ("L=151.234 mm", 151.234), ("1.5e2 mm", 150.0),
    ("-1.5E-1mm", -0.15), (".5 mm", 0.5), ("+42 mm", 42.0),
])
def test_the_default_level_pattern_reads_whole_lines_in_mm(line, value):
    pattern = _level_config()["pattern"]
    assert sensors.parse_line(line, pattern) == (pytest.approx(value), "mm", True)


@pytest.mark.parametrize("line,why", [
    ("15.02 cm", "is in 'cm', the sensor is set to read 'mm'"),  # before: 15.02 mm
    ("ERR 42", "not a level reading: 'ERR 42'"),  # before: 42 mm, stable
    ("150,2 mm", "not a level reading: '150,2 mm'"),  # before: 150 mm
    ("OVERRANGE 9999.9", "not a level reading: 'OVERRANGE 9999.9'"),  # before: 9999.9 mm, stable
    ("9999.9 OVERRANGE", "is in 'OVERRANGE'"),
    ("1.2.3 mm", "not a level reading"),
    ("151.2", "'151.2' has no unit"),
])
def test_the_default_level_pattern_refuses_other_lines_naming_them(line, why):
    with pytest.raises(SensorError, match=re.escape(why)):
        sensors.parse_line(line, _level_config()["pattern"])


def test_a_bare_number_is_read_only_when_the_config_allows_it():
    pattern = _level_config()["pattern"]
    assert sensors.parse_line("151.2", pattern, unit_optional=True) == (151.2, "mm", True)
    with pytest.raises(SensorError, match="in 'cm'"):
        sensors.parse_line("151.2 cm", pattern, unit_optional=True)
    with pytest.raises(ValueError, match="no named group 'value'"):
        sensors.LineSensor("loop://", pattern=r"\d+")


def _level_config() -> dict:
    """``conf/sensor/level.yaml``'s ``device`` node."""
    import yaml

    return yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "sensor" / "level.yaml")
                          .read_text())["device"]


def test_a_sensor_sending_error_lines_fails_the_reading_naming_the_line(world):
    sensor = sensors.LineSensor(world.url("level"), timeout=0.5, max_lines=3)
    sensor.connect()
    try:
        assert sensor.read().value == pytest.approx(world.tank.rest_level_mm, abs=1e-3)  # the fake's 'L=... mm'
        world.sensor_format.level_format = "ERR 42"
        with pytest.raises(SensorError, match=r"gave no reading in 3 line\(s\); the last: not a level reading: "
                                              r"'ERR 42'"):
            sensor.read()
        world.sensor_format.level_format = "{value:.3f} cm"
        with pytest.raises(SensorError, match="is in 'cm'"):
            sensor.read()
    finally:
        world.sensor_format.level_format = "L={value:.3f} mm"
        sensor.close()


def test_balance_lines_that_are_not_readings_are_refused():
    for bad, word in (("ST,1.2.3 g", "not an A&D"), ("ST,+00123,45 g", "not an A&D"), ("ST,+00123.45", "no unit"),
                      ("ST,+00123.45 lb", "unknown unit 'lb'"), ("EC,E11", "not an A&D")):
        with pytest.raises(SensorError, match=re.escape(word)):
            sensors.parse_ad(bad)
    assert sensors.parse_ad("ST,+1.2345E+02  g") == (pytest.approx(123.45), "g", True)
    for bad, word in (("S S 1.2.3 g", "not an MT-SICS"), ("S S   100,00 g", "not an MT-SICS"),
                      ("S S   100.00", "not an MT-SICS"), ("S S   100.00 lb", "unknown unit 'lb'")):
        with pytest.raises(SensorError, match=re.escape(word)):
            sensors.parse_sics(bad)


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


def test_an_average_holding_nan_or_inf_is_not_stable_and_warns_of_nothing():
    """Before: a NaN or inf among the averaged readings gave numpy's "invalid value encountered in subtract" and,
    for NaN, a reading marked stable (NaN > max_spread is false)."""
    from dipnet.rig.sensors import AveragingSensor, Reading

    class Values:
        quantity = "level_mm"

        def __init__(self, values):
            self.values = list(values)

        def read(self):
            return Reading(self.values.pop(0), "mm", True)

    for bad in (float("nan"), float("inf")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            reading = AveragingSensor(Values([150.0, bad, 150.0]), n=3, max_spread=0.05).read()
        assert not reading.stable
    assert AveragingSensor(Values([150.0, 150.01, 150.0]), n=3, max_spread=0.05).read().stable


def test_a_sensor_time_limit_or_terminator_that_cannot_work_is_refused_before_connecting():
    """Before: ``sensor.device.timeout=-1`` stopped the scan after moving (a RigTimeout "within 0 s"), and
    ``sensor.device.terminator=''`` read empty lines until "gave no reading in 5 line(s)", exit 3."""
    from dipnet.rig.sensors import BalanceSensor, LineSensor

    with pytest.raises(ValueError, match=r"^sensor\.device\.timeout must be a positive number of seconds .*got -1$"):
        LineSensor("fakerig://nowhere/level", timeout=-1)
    with pytest.raises(ValueError, match=r"^sensor\.device\.timeout must be a positive number .*got 0$"):
        BalanceSensor("fakerig://nowhere/ad", timeout=0)
    with pytest.raises(ValueError, match=r"^sensor\.device\.terminator is empty"):
        LineSensor("fakerig://nowhere/level", terminator="")


def test_an_averaging_that_cannot_work_is_refused_before_anything_moves():
    """Before: ``sensor.average.interval_s=-1`` stopped the scan at its first reading with "ValueError: sleep length
    must be non-negative"; ``sensor.average.max_spread=-1`` with "SensorUnstable: sensor not stable after 3 readings"
    (exit 3 both, after the object had moved)."""
    from dipnet.rig.sensors import AveragingSensor, LineSensor

    device = LineSensor("fakerig://nowhere/level")
    with pytest.raises(ValueError, match=r"^sensor\.average\.interval_s must be a number of seconds >= 0 .*got -1$"):
        AveragingSensor(device, n=3, interval_s=-1)
    with pytest.raises(ValueError, match=r"^sensor\.average\.max_spread must be a number >= 0 .*got -1"):
        AveragingSensor(device, n=3, max_spread=-1)
    assert AveragingSensor(device, n=3, max_spread=None, interval_s=0).max_spread is None


@pytest.mark.parametrize("n, message", [(1.5, r"got 1.5 \(2.5 is not cut to 2\)"), (True, r"got True"),
                                        ("3", r"got '3'"), (0, r">= 1, got 0")])
def test_an_averaging_count_that_is_not_a_whole_number_is_refused_naming_the_option(n, message):
    """Before: ``sensor.average.n=1.5`` (or ``true``) averaged 1 reading, exit 0, without a word; 0 was refused as
    "n must be >= 1", naming no option."""
    from dipnet.rig.sensors import AveragingSensor, LineSensor

    with pytest.raises(ValueError, match=r"^sensor\.average\.n must be a whole number.*" + message):
        AveragingSensor(LineSensor("fakerig://nowhere/level"), n=n)
    assert AveragingSensor(LineSensor("fakerig://nowhere/level"), n=3.0).n == 3


class _MidLineStream:
    """A pyserial-like port of a level sensor streaming ``L=151.234 mm`` lines: dropping its input
    (``reset_input_buffer``) lands in the middle of the line then on the wire, as a real serial stream does."""

    port = "stream://"

    def __init__(self) -> None:
        self.data = bytearray()

    def reset_input_buffer(self) -> None:
        self.data = bytearray(b"234 mm\r\nL=151.240 mm\r\nL=151.246 mm\r\n")  # 'L=151.' was dropped

    @property
    def in_waiting(self) -> int:
        return len(self.data)

    def read(self, size: int = 1) -> bytes:
        chunk, self.data = bytes(self.data[:size]), self.data[size:]
        return chunk

    def close(self) -> None:
        pass


def test_a_streaming_sensor_never_reads_the_tail_of_a_line_cut_by_dropping_stale_input():
    """Before: the first line after the stale input was dropped, ``234 mm`` (the tail of ``L=151.234 mm``), read as a
    stable level of 234 mm (a partial line lands there whenever the drop falls inside a line on the wire)."""
    from dipnet.rig.controller import LineChannel

    sensor = sensors.LineSensor("stream://", terminator="\\r\\n", timeout=0.2)
    sensor.link = LineChannel(_MidLineStream(), b"\r\n")
    assert sensor.read() == sensors.Reading(151.24, "mm", True)


class _Replies:
    """A link whose every query is answered by the next of ``replies`` (a balance's lines, as read)."""

    def __init__(self, replies: list[str]) -> None:
        self.replies, self.queries = list(replies), 0

    def discard_input(self) -> None:
        pass

    def write(self, data: bytes) -> None:
        self.queries += 1

    def read_line(self, timeout: float) -> str:
        return self.replies.pop(0)


def _balance(style: str, replies: list[str], **options) -> tuple[sensors.BalanceSensor, _Replies]:
    balance, link = sensors.BalanceSensor("fakerig://nowhere/" + style, style=style, **options), _Replies(replies)
    balance._link = lambda: link
    return balance, link


@pytest.mark.parametrize("style,garbled,good", [
    ("ad", ["ST,+001\x0023.45  g", "ST,+00123.45"], "ST,+00123.45  g"),  # a byte flipped, a reply cut short
    ("sics", ["S S   1\xff0.00 g", "ET"], "S S     123.45 g"),  # a byte flipped, a transmission error
])
def test_a_garbled_balance_reply_is_asked_again_and_not_recorded(style, garbled, good):
    """Before: one garbled reply (a byte lost or flipped on the wire) stopped the scan ("SensorError: not an A&D
    balance line"), though the next query would have been answered."""
    balance, link = _balance(style, [*garbled, good])
    assert balance.read() == (pytest.approx(123.45), "g", True) and link.queries == 3
    balance, link = _balance(style, [*garbled, garbled[0], good])
    with pytest.raises(sensors.GarbledReply, match=r"gave 3 garbled replies to one query .*check the cable"):
        balance.read()
    assert link.queries == 3


@pytest.mark.parametrize("style,reply,error", [
    ("ad", "OL,+9999999E+19", "overload"), ("ad", "QT,+00012345 PC", "counting"),
    ("ad", "ST,+00123.45 lb", "unknown unit 'lb'"), ("sics", "S +", "overload"), ("sics", "ES", "syntax"),
])
def test_an_error_the_balance_reports_is_not_asked_again(style, reply, error):
    balance, link = _balance(style, [reply, "never read"])
    with pytest.raises(SensorError, match=error) as caught:
        balance.read()
    assert not isinstance(caught.value, sensors.GarbledReply) and link.queries == 1


def test_a_busy_balance_is_asked_again_up_to_its_busy_retries():
    balance, link = _balance("sics", ["S I", "S I", "S S     100.00 g"], busy_retries=2)
    assert balance.read() == (100.0, "g", True) and link.queries == 3
    balance, link = _balance("sics", ["S I"] * 3, busy_retries=1)
    with pytest.raises(SensorError, match="stayed busy for 2 queries"):
        balance.read()
    for name in ("busy_retries", "garbled_retries"):
        for bad in (-1, 1.5, True):
            with pytest.raises(ValueError, match=rf"^sensor\.device\.{name} must be a whole number >= 0"):
                sensors.BalanceSensor("fakerig://nowhere/ad", **{name: bad})


def test_unit_optional_given_as_another_word_is_refused():
    """``sensor.device.unit_optional=no`` was ``bool("no")``, true: a bare number was read in mm."""
    with pytest.raises(ValueError, match="sensor.device.unit_optional must be true or false, got 'no'"):
        sensors.LineSensor("loop://", unit_optional="no")
