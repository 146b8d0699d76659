"""The fake Marlin 2.x controller (line numbers and checksums).

Its planner keeps the machine position it last commanded (:attr:`MarlinDevice.planned`, by axis letter): ``M114``
reports it in logical coordinates (plus the workspace offset: ``FakeRig.marlin_offset``, changed by ``G92``) and,
after ``Count``, in steps (``FakeRig.marlin_steps``, which ``M92`` reports and sets), as Marlin 2.x's
``report_current_position_projected`` does; moves take logical coordinates, and the motors turn by the steps counted
(an ``M92`` other than ``FakeRig.marlin_motor_steps`` moves them too far or not far enough). A ``stall`` fault stops the
stage half-way while the planner keeps the target, and says ``echo:endstops hit:``."""

from __future__ import annotations

import math
import re
import time

from dipnet.rig import marlin
from dipnet.rig.fake.device import Device, parse_words


class MarlinDevice(Device):
    """A Marlin 2.x controller (line numbers + checksums checked when present)."""

    def on_open(self) -> None:
        self.last_n = 0
        self.stopped = False
        self.corrupt_next = False
        self.planned = self.world.machine_position()  # machine coordinates the planner last commanded
        self.shift = dict(self.world.marlin_offset)  # logical minus machine coordinates (M206, G92)
        self.emit("start")
        self.emit("echo:Marlin 2.1.2.1")
        self.emit("echo: Last Updated: 2023-05-25 | Author: (dipnet fake rig)")

    def parse_input(self) -> None:
        for line in self.lines():
            if line:
                with self.world.lock:
                    self.line(line)

    def resend(self, reason: str) -> None:
        self.emit(f"Error:{reason}, Last Line: {self.last_n}")
        self.emit(f"Resend: {self.last_n + 1}")
        self.emit("ok")

    def line(self, raw: str) -> None:
        w = self.world
        text = raw
        m = re.match(r"^N(-?\d+)\s+(.*?)\*(\d+)$", raw)
        if m:
            n, body, cs = int(m[1]), m[2], int(m[3])
            if cs != marlin.checksum(raw[:raw.rindex("*")]) or self.corrupt_next:
                self.corrupt_next = False
                self.resend("checksum mismatch")
                return
            if body.upper().startswith("M110"):
                self.last_n = int(parse_words(body).get("N", n))
                self.emit("ok")
                return
            if n != self.last_n + 1:
                self.resend("Line Number is not Last Line Number+1")
                return
            self.last_n = n
            text = body
        upper = text.upper().strip()
        code = upper.split()[0] if upper else ""
        if code == "M110":
            self.last_n = int(parse_words(upper[4:]).get("N", 0))
            self.emit("ok")
        elif code == "M999":
            self.stopped = False
            self.emit("ok")
        elif self.stopped:
            self.emit("Error:Printer stopped due to errors. Fix the error and use M999 to restart.")
            self.emit("ok")
        elif code in ("G0", "G1", "G00", "G01"):
            fault = w.on_motion()
            kind = None if fault is None else fault.kind
            if kind == "error":
                self.emit("Error:Move out of range")
                self.emit("ok")
                return
            if kind == "disconnect":
                self.dead = True
                return
            if kind == "reset":
                w.halt()
                self.on_open()
                return
            if kind == "resend":
                self.last_n -= 1
                self.resend("checksum mismatch")
                return
            moved = self.move(parse_words(re.sub(r"^G0*[01]|\bF[-+\d.]+", "", upper)), stall=kind == "stall")
            if kind == "alarm":
                w.halt()
                self.stopped = True
                self.emit("Error:Printer stopped due to errors. Fix the error and use M999 to restart.")
                self.emit("ok")
                return
            if kind != "drop":
                self.emit("ok")
            if kind == "stall":  # Endstops::event_handler, in the idle loop once the axis stopped
                end = w.machine_position(w._move[1])
                self.emit("echo:endstops hit: " + "".join(f" {a}:{end[a]:.2f}" for a in moved), at=w.move_end())
        elif code == "G28":
            w.start_move({"lower_mm": 0.0, "tilt_deg": 0.0, "spin_deg": 0.0})
            self.planned, self.shift = w.machine_position(w._move[1]), dict(w.marlin_offset)  # G28 clears G92
            self.wait_ok()
        elif code == "M400":
            self.wait_ok()
        elif code == "M114":
            logical = {a: v + self.shift.get(a, 0.0) for a, v in self.planned.items()}
            counts = " ".join(f"{a}:{round(v * w.marlin_steps[a])}" for a, v in self.planned.items())
            self.emit(f"{' '.join(f'{a}:{v:.2f}' for a, v in logical.items())} E:0.00 Count {counts}")
            self.emit("ok")
        elif code == "M410":
            w.halt()
            self.planned = w.machine_position()  # quickstop_stepper: the planner takes the steppers' position
            self.emit("ok")
        elif code == "G92":
            self.shift.update({a: v - self.planned[a] for a, v in parse_words(upper[3:]).items() if a in self.planned})
            self.emit("ok")
        elif code == "M92":
            self.steps_per_unit(parse_words(upper[3:]))
        elif code == "M503" and w.marlin_reports_steps:
            self.emit("echo:; Steps per unit:")
            self.emit(f"echo:  M92 {self.steps_text()}")
            self.emit("echo:; Home offset:")
            self.emit(f"echo:  M206 {' '.join(f'{a}{w.marlin_offset.get(a, 0.0):.2f}' for a in self.planned)}")
            self.emit("ok")
        elif code in ("G90", "G91", "G21", "M17", "M18", "M84", "M115"):
            self.emit("ok")
        else:
            self.emit(f'echo:Unknown command: "{text}"')
            self.emit("ok")

    def move(self, words: dict[str, float], stall: bool) -> list[str]:
        """Plan a move to logical coordinates ``words`` (by axis letter), clamped to the software endstops in machine
        coordinates (``FakeRig.marlin_soft_limits``): the steppers move the stage by the change of the planned
        machine position in steps over the steps the motors need per unit (all of it, or half if they ``stall``).
        Returns the letters moved."""
        w = self.world
        native = {a: min(max(v - self.shift.get(a, 0.0), low), high) for a, v in words.items() if a in self.planned
                  for low, high in [w.marlin_soft_limits.get(a, (-math.inf, math.inf))]}
        here, share = w.machine_position(), 0.5 if stall else 1.0
        w.start_move(w.target_from_words({a: here[a] + share * (v - self.planned[a]) * w.marlin_steps[a]
                                          / w.marlin_motor_steps[a] for a, v in native.items()}))
        self.planned.update(native)
        return list(native)

    def steps_per_unit(self, words: dict[str, float]) -> None:
        """``M92``: set the given axes' steps per unit (the planner keeps its position in units), or with no
        axes report them as Marlin 2.0.9+ does (no ``echo:``), or answer only ``ok`` as Marlin 1.x."""
        w = self.world
        w.marlin_steps.update({a: v for a, v in words.items() if a in w.marlin_steps})
        if not words and w.marlin_reports_steps:
            self.emit(f"  M92 {self.steps_text()}")
        self.emit("ok")

    def steps_text(self) -> str:
        steps = self.world.marlin_steps
        return " ".join(f"{a}{steps[a]:.2f}" for a in [*self.planned, "E"] if a in steps)

    def wait_ok(self) -> None:
        """``ok`` when the move ends, with ``echo:busy: processing`` every keep-alive interval."""
        now, end = time.monotonic(), self.world.move_end()
        t = now + self.world.keepalive_s
        while t < end:
            self.emit("echo:busy: processing", at=t)
            t += self.world.keepalive_s
        self.emit("ok", at=max(end, now))
