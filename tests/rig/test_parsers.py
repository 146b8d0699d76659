"""Pure parsers of the rig protocols, on recorded-style transcripts."""

from __future__ import annotations

import functools
import operator

import pytest

from dipnet.rig import grbl_dialect as grbl, marlin, sensors
from dipnet.rig.controller import Axis, AxisMap, ControllerError, Position

# A GRBL 1.1 session: reset banner, alarm message, status reports with different $10 masks.
GRBL_TRANSCRIPT = """\
Grbl 1.1h ['$' for help]
[MSG:'$H'|'$X' to unlock]
ok
error:9
ALARM:1
[MSG:Reset to continue]
[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]
<Idle|MPos:0.000,0.000,-25.000,10.000,40.000|FS:0,0|WCO:0.000,0.000,0.000>
<Run|WPos:1.000,2.000,-3.000,4.000,5.000|Bf:15,128|FS:500,0|WCO:0.500,0.500,-1.000,0.000,0.000>
<Hold:0|MPos:0.000,0.000,-12.500,0.000,0.000|FS:0,0|Pn:Z|Ov:100,100,100|A:SF>
"""

# A Marlin 2.x session with keep-alives, a checksum error and a halt.
MARLIN_TRANSCRIPT = """\
start
echo:Marlin 2.1.2.1
echo: Last Updated: 2023-05-25 | Author: (none)
ok
echo:busy: processing
busy: processing
X:0.00 Y:0.00 Z:-25.00 A:10.00 B:40.00 E:0.00 Count X:0 Y:0 Z:-10000 A:800 B:3200
ok P15 B3
Error:checksum mismatch, Last Line: 11
Resend: 12
echo:Unknown command: "G999"
Error:Printer halted. kill() called!
"""


def test_grbl_transcript_classification():
    kinds = [grbl.classify(line) for line in GRBL_TRANSCRIPT.splitlines()]
    assert [k.kind for k in kinds] == ["banner", "msg", "ok", "error", "alarm", "msg", "feedback",
                                       "status", "status", "status"]
    assert kinds[0].payload == "1.1h"
    assert kinds[1].payload == "'$H'|'$X' to unlock"
    assert (kinds[3].code, kinds[4].code) == (9, 1)
    assert "alarm or jog" in grbl.describe("error", 9) and "hard limit" in grbl.describe("alarm", 1)


def test_grbl_status_by_key():
    lines = GRBL_TRANSCRIPT.splitlines()
    idle = grbl.parse_status(lines[7])
    assert idle.state == "Idle" and idle.substate is None
    assert idle.mpos == {"X": 0.0, "Y": 0.0, "Z": -25.0, "A": 10.0, "B": 40.0}
    run = grbl.parse_status(lines[8])  # only WPos: machine = WPos + WCO
    assert run.state == "Run" and run.fields["Bf"] == "15,128"
    assert run.mpos == pytest.approx({"X": 1.5, "Y": 2.5, "Z": -4.0, "A": 4.0, "B": 5.0})
    hold = grbl.parse_status(lines[9])
    assert (hold.state, hold.substate, hold.fields["Pn"]) == ("Hold", 0, "Z")
    three = grbl.parse_status("<Idle|MPos:1.000,2.000,3.000|FS:0,0>", axes="XYZ")
    assert three.mpos == {"X": 1.0, "Y": 2.0, "Z": 3.0}
    assert grbl.parse_status("<Idle|FS:0,0>").mpos is None
    with pytest.raises(ValueError, match="coordinates"):
        grbl.parse_status("<Idle|MPos:1,2,3>", axes="XYZAB")
    with pytest.raises(ValueError, match="not a GRBL status"):
        grbl.parse_status("ok")


def test_axis_map_round_trip_and_words():
    axes = AxisMap(lower=Axis("Z", scale=2.0, sign=-1, offset=5.0), tilt=Axis("A", scale=10.0), spin=Axis("B"))
    assert axes.words(12.5, 3.0, None) == "Z-20.0000 A30.0000"
    pos = axes.rig_position({"Z": -20.0, "A": 30.0, "B": 7.0, "X": 0.0})
    assert pos == Position(12.5, 3.0, 7.0)
    with pytest.raises(ControllerError, match="no B axis"):
        axes.rig_position({"Z": 0.0, "A": 0.0})
    with pytest.raises(ValueError, match="distinct"):
        AxisMap(lower=Axis("Z"), tilt=Axis("Z"), spin=Axis("B"))
    cfg = AxisMap.from_config({"tilt": {"letter": "X"}, "spin": {"letter": "Y", "sign": -1}})
    assert (cfg.lower.letter, cfg.lower.sign, cfg.tilt.letter, cfg.spin.sign) == ("Z", -1, "X", -1)


def test_marlin_transcript_classification():
    kinds = [marlin.classify(line) for line in MARLIN_TRANSCRIPT.splitlines()]
    assert [k.kind for k in kinds] == ["start", "echo", "echo", "ok", "busy", "busy", "position", "ok",
                                       "error", "resend", "echo", "fatal"]
    assert kinds[9].number == 12
    assert marlin.classify("rs N7").number == 7
    assert marlin.parse_position(MARLIN_TRANSCRIPT.splitlines()[6]) == {
        "X": 0.0, "Y": 0.0, "Z": -25.0, "A": 10.0, "B": 40.0, "E": 0.0}
    assert marlin.parse_position("echo:busy: processing") == {}


def test_marlin_checksum():
    # OctoPrint's well-known first line
    assert marlin.numbered(0, "M110 N0") == "N0 M110 N0*125"
    text = "N12 G0 Z-10.0000 A5.0000"
    assert marlin.checksum(text) == functools.reduce(operator.xor, text.encode("ascii"))


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
