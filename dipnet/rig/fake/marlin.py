"""The fake Marlin 2.x controller (line numbers and checksums)."""

from __future__ import annotations

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
            w.start_move(w.target_from_words(parse_words(re.sub(r"^G0*[01]|\bF[-+\d.]+", "", upper))))
            if kind == "alarm":
                w.halt()
                self.stopped = True
                self.emit("Error:Printer stopped due to errors. Fix the error and use M999 to restart.")
                self.emit("ok")
                return
            if kind != "drop":
                self.emit("ok")
        elif code == "G28":
            w.start_move({"lower_mm": 0.0, "tilt_deg": 0.0, "spin_deg": 0.0})
            self.wait_ok()
        elif code == "M400":
            self.wait_ok()
        elif code == "M114":
            pos = w.machine_position()
            axes = " ".join(f"{a}:{pos[a]:.2f}" for a in pos)
            self.emit(f"{axes} E:0.00 Count {' '.join(f'{a}:{round(pos[a] * 400)}' for a in pos)}")
            self.emit("ok")
        elif code == "M410":
            w.halt()
            self.emit("ok")
        elif code in ("G90", "G91", "G92", "G21", "M17", "M18", "M84", "M115"):
            self.emit("ok")
        else:
            self.emit(f'echo:Unknown command: "{text}"')
            self.emit("ok")

    def wait_ok(self) -> None:
        """``ok`` when the move ends, with ``echo:busy: processing`` every keep-alive interval."""
        now, end = time.monotonic(), self.world.move_end()
        t = now + self.world.keepalive_s
        while t < end:
            self.emit("echo:busy: processing", at=t)
            t += self.world.keepalive_s
        self.emit("ok", at=max(end, now))
