"""GRBL's wire language (dipnet.rig.grbl_dialect): every line of a recorded-style transcript classified, status
reports parsed by key."""

from __future__ import annotations

import pytest

from dipnet.rig import grbl_dialect as grbl

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
