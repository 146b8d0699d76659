"""The fake GRBL 1.1 controller, following the real firmware's recorded replies."""

from __future__ import annotations

import re

from dipnet.rig.fake.device import Device, parse_words

_GRBL_BANNER = "Grbl 1.1h ['$' for help]"


class GrblDevice(Device):
    """A GRBL 1.1 controller (resets when the port opens, like an Arduino on DTR); see the
    module docstring for what it reproduces from the recorded firmware."""

    def on_open(self) -> None:
        self.hold = None  # None, or the substate to report next (1 while decelerating, then 0)
        self.held_target: dict | None = None  # the rest of the held move
        self.held_dwell = False  # a G4 P0 waiting for the hold to end
        self.door = False
        self.late_s = 0.0
        self.status_fault: str | None = None
        self.world.critical = False
        self.banner()
        self.run_startup()

    def run_startup(self) -> None:
        """After a reset GRBL is back in mm (``G21``), then runs its startup block (``$N0``), which may hold ``G20``."""
        self.inches = bool(re.search(r"\bG20\b", self.world.grbl_startup))

    def banner(self) -> None:
        self.emit("")
        self.emit(_GRBL_BANNER)
        if self.world.alarm:
            self.emit("[MSG:'$H'|'$X' to unlock]")

    def parse_input(self) -> None:
        w = self.world
        while self._inbuf:
            for i, byte in enumerate(self._inbuf):  # real-time commands act at once, even mid-line
                if byte in b"?!~\x18":
                    del self._inbuf[i]
                    with w.lock:
                        self.realtime(byte)
                    break
            else:
                break
        for line in self.lines():
            if line and not w.critical:
                with w.lock:
                    self.line(line)

    def state(self) -> str:
        w = self.world
        if w.alarm:
            return "Alarm"
        if self.door:
            return "Door:1"
        if self.hold is not None:
            state = f"Hold:{self.hold}"
            self.hold = 0  # the hold completes after one report of Hold:1
            return state
        return "Run" if w.moving() else "Idle"

    def report(self) -> None:
        w = self.world
        mpos = w.machine_position()
        kind = "MPos" if int(w.grbl_settings.get(10, 1)) & 1 else "WPos"  # work offsets are 0 here
        text = f"<{self.state()}|{kind}:{','.join(f'{mpos[a]:.3f}' for a in w.status_axes)}|FS:0,0>"
        if self.status_fault == "corrupt_status":  # as in t3f.log: '|' read as ':'
            text = text.replace("|FS", ":FS")
        elif self.status_fault == "split_status":  # as in t3g.log: one byte became a newline
            cut = text.rindex("|") + 2
            text = text[:cut] + "\n" + text[cut + 1:]
        self.status_fault = None
        self.emit(text, realtime=True)

    def realtime(self, byte: int) -> None:
        w = self.world
        if byte == 0x18:
            self.soft_reset()
        elif w.critical:
            return  # only a reset is heard
        elif byte == ord("?"):
            self.report()
        elif byte == ord("!") and w.moving() and self.hold is None:
            self.start_hold(dict(zip(("lower_mm", "tilt_deg", "spin_deg"), vars(w._move[1]).values())))
        elif byte == ord("~") and self.hold is not None and not self.door:
            self.hold = None
            if self.held_target is not None:
                w.start_move(self.held_target)
                self.held_target = None
            if self.held_dwell:
                self.held_dwell = False
                self.emit("ok", at=w.move_end())

    def start_hold(self, target: dict) -> None:
        self.world.halt()
        self.hold, self.held_target = 1, target

    def soft_reset(self) -> None:
        """0x18: stop at once; a reset while moving or decelerating loses the position (ALARM:3);
        a held dwell is answered first, as the recorded firmware does."""
        w = self.world
        self.clear_output()
        if w.moving() or self.hold == 1:
            w.alarm = True
            self.emit("ALARM:3")
        w.halt()
        if self.held_dwell:
            self.emit("ok")
        self.hold, self.held_target, self.held_dwell = None, None, False
        w.critical = False
        self.banner()
        self.run_startup()

    def alarm(self, code: int) -> None:
        w = self.world
        w.halt()
        w.alarm = True
        self.emit(f"ALARM:{code}")
        if code in (1, 2):
            self.emit("[MSG:Reset to continue]")
            w.critical = True

    def system(self, upper: str) -> None:
        """``$`` commands."""
        w = self.world
        settings = w.grbl_settings
        if upper == "$X":
            w.alarm = False
            self.emit("[MSG:Caution: Unlocked]")
            self.emit("ok")
        elif upper == "$H":
            if not settings.get(22):
                self.emit("error:5")
                return
            w.start_move({"lower_mm": 0.0, "tilt_deg": 0.0, "spin_deg": 0.0})
            w.alarm = False
            self.emit("ok", at=w.move_end())
        elif upper == "$$":
            for key in sorted(settings):
                value = settings[key]
                self.emit(f"${key}={value:.3f}" if isinstance(value, float) else f"${key}={value}")
            self.emit("ok")
        elif upper == "$I":
            self.emit("[VER:1.1h.20190830:]")
            self.emit("[OPT:V,15,128]")
            self.emit("ok")
        elif re.match(r"^\$\d+=", upper):
            key, value = upper[1:].split("=", 1)
            settings[int(key)] = float(value) if "." in value else int(value)
            self.emit("ok")
        else:
            self.emit("ok")

    def outside_soft_limits(self, words: dict[str, float]) -> bool:
        settings = self.world.grbl_settings
        if not (settings.get(20) and settings.get(22)):
            return False
        return any(not (-settings.get(130 + "XYZABC".index(a), 0.0) <= v <= 0.0) for a, v in words.items()
                   if a in "XYZABC")

    def line(self, line: str) -> None:
        w = self.world
        upper = line.upper()
        if upper.startswith("$"):
            self.system(upper)
        elif w.alarm:
            self.emit("error:9")
        elif re.search(r"\bG0*4\b", upper):
            if self.hold is not None or self.door:
                self.held_dwell = True
            else:
                self.emit("ok", at=w.move_end() + self.late_s)
            self.late_s = 0.0
        elif re.search(r"\bG0*[01]\b", upper):
            self.motion(upper)
        elif re.match(r"^(G9[01]|G2[01]|G5[4-9]|M[0-9]+)\b", upper):
            units = re.findall(r"\bG2([01])\b", upper)
            if units:
                self.inches = units[-1] == "0"
            self.emit("ok")
        else:
            self.emit("error:20")

    def motion(self, upper: str) -> None:
        w = self.world
        fault = w.on_motion()
        kind = None if fault is None else fault.kind
        if kind == "error":
            self.emit(f"error:{fault.code}")
            return
        if kind == "reset":  # a power glitch: the board restarts
            w.halt()
            w.alarm = bool(w.grbl_settings.get(22))
            self.on_open()
            return
        words = parse_words(re.sub(r"\bG\d+\b|\bF[-+\d.]+", "", upper))
        if self.inches:  # G20 scales the linear axes' words (X, Y, Z: also a turn sent as X or Y), not A, B, C
            words = {k: v * 25.4 if k in "XYZ" else v for k, v in words.items()}
        if self.outside_soft_limits(words):
            self.alarm(2)
            return
        target = w.target_from_words(words)
        if kind == "disconnect":  # the link dies with the move under way (t4e2, t4e3)
            w.start_move(target)
            self.dead = True
            return
        if kind == "alarm":
            w.start_move(target)
            self.alarm(fault.code)
            return
        if kind == "hold":  # lands half-way
            here = w.position()
            half = {k: None if v is None else (getattr(here, k) + v) / 2 for k, v in target.items()}
            w.start_move(half)
            self.emit("ok")
            self.start_hold(target)
            return
        w.start_move(target)
        if kind == "door":
            w.halt()
            self.door = True
        elif kind == "late_ok":
            self.late_s = fault.delay_s
        elif kind in ("corrupt_status", "split_status"):
            self.status_fault = kind
        if kind != "drop":
            self.emit("ok")
