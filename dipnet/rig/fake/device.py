"""One end of a link to the fake world: bytes in, timed bytes out."""

from __future__ import annotations

import re
import threading
import time
from collections import deque

from dipnet.rig.fake.world import FakeRig


# ============================================================================ devices
class Device:
    """One end of a link to the world: bytes in (:meth:`receive`), timed bytes out (:meth:`read`)."""

    streaming = False

    def __init__(self, world: FakeRig) -> None:
        self.world = world
        self.out: deque[tuple[float, bytes]] = deque()
        self.cond = threading.Condition()
        self.dead = False
        self._inbuf = bytearray()
        self.on_open()

    def on_open(self) -> None:
        """Called once when the link opens (banners)."""

    def emit(self, text: str | bytes, at: float | None = None, terminator: bytes = b"\r\n",
             realtime: bool = False) -> None:
        """Queue output ready at ``at`` (default now) plus the latency. Ordinary output keeps its
        order (a reply scheduled late holds back the replies after it, as a firmware answering
        lines in order does); ``realtime`` output (status reports) overtakes it."""
        data = text if isinstance(text, bytes) else text.encode("ascii") + terminator
        ready = (time.monotonic() if at is None else at) + self.world.latency_s
        with self.cond:
            if realtime:
                i = len(self.out)
                while i and self.out[i - 1][0] > ready:
                    i -= 1
                self.out.insert(i, (ready, data))
            else:
                ready = max([ready] + [t for t, _ in self.out])
                self.out.append((ready, data))
            self.cond.notify_all()

    def receive(self, data: bytes) -> None:
        self._inbuf += data
        self.parse_input()

    def parse_input(self) -> None:
        """Consume ``self._inbuf``."""

    def poll(self) -> None:
        """Periodic work (streaming, keep-alives); called before every read."""

    def take(self, size: int, timeout: float | None) -> bytes:
        """Up to ``size`` ready bytes, waiting at most ``timeout`` s for the first ones."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.cond:
            while True:
                self.poll()
                now = time.monotonic()
                if self.out and self.out[0][0] <= now:
                    ready, data = self.out.popleft()
                    if len(data) > size:
                        self.out.appendleft((ready, data[size:]))
                        data = data[:size]
                    return data
                if self.streaming and not self.out:
                    self.stream_line()
                    continue
                wait = 0.005 if not self.out else min(0.005, self.out[0][0] - now)
                if deadline is not None:
                    if now >= deadline:
                        return b""
                    wait = min(wait, deadline - now)
                self.cond.wait(max(wait, 1e-4))

    def pending(self) -> int:
        now = time.monotonic()
        with self.cond:
            return sum(len(d) for t, d in self.out if t <= now)

    def clear_output(self) -> None:
        with self.cond:
            self.out.clear()

    def stream_line(self) -> None:
        """Produce one line of a streaming sensor."""

    def lines(self, terminator: bytes = b"\n"):
        while True:
            end = self._inbuf.find(terminator)
            if end < 0:
                return
            line = bytes(self._inbuf[:end]).decode("ascii", errors="replace").strip()
            del self._inbuf[:end + len(terminator)]
            yield line


def parse_words(line: str) -> dict[str, float]:
    """The G-code words of a line: ``{letter (upper case): value}``."""
    return {m[1].upper(): float(m[2]) for m in re.finditer(r"([A-Za-z])\s*([-+]?\d*\.?\d+)", line)}
