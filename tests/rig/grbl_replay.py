"""Replay of recorded GRBL wire logs (``tests/data/grbl-traces``) as a pyserial-like port.

A log line is ``TIME DIR BYTES`` (``>>`` host to GRBL, ``<<`` GRBL to host, ``!!`` bytes the
test bridge injected, ``##`` bridge events). :class:`ReplayPort` plays the firmware's side of
one recorded session: every chunk the driver writes is compared with the next recorded host
chunk; when it matches, the firmware's recorded output up to the following host chunk becomes
readable. A chunk found in ``extras`` (recorded replies keyed by host chunk) is answered from
there without advancing the script, so a driver may send extra queries (``$$``, ``$I``). The
first other chunk that differs ends the script: from then on ``answers`` reply (recorded or
documented replies keyed by host chunk, used in order, the last one repeating), everything
else meets silence. :attr:`sent` keeps every chunk written and :attr:`diverged_at` the index in
``sent`` where the driver left the recording. Where the bridge dropped the connection the
port fails as a dropped socket does: reads once the output before the drop is consumed, and
writes, raise ``SerialException``.
"""

from __future__ import annotations

import ast
import time
from collections import defaultdict
from pathlib import Path

from serial import SerialException

TRACES = Path(__file__).parents[1] / "data" / "grbl-traces"


DROP = ("##", b"connection dropped")  # the script entry where the bridge dropped the connection


def read_trace(name: str) -> list[list[tuple[str, bytes]]]:
    """The sessions of ``TRACES/name`` (split at ``client connected``), each a list of
    ``(direction, bytes)``; a dropped connection is the entry :data:`DROP`."""
    sessions: list[list[tuple[str, bytes]]] = [[]]
    for line in (TRACES / name).read_text().splitlines():
        parts = line.split(None, 2)
        if len(parts) < 3 or parts[1] not in (">>", "<<", "!!", "##"):
            continue
        direction, payload = parts[1], ast.literal_eval(parts[2])
        if direction == "##":
            if payload == "client connected":
                sessions.append([])
            elif payload.startswith("connection dropped"):
                sessions[-1].append(DROP)
            continue
        sessions[-1].append((direction, payload))
    return [s for s in sessions if s]


def asked_first(session: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    """``session`` as the driver now opens it: a ``?`` before the recorded soft reset, answered
    with the status the firmware reported right after that reset (for a machine at rest a reset
    changes neither its state nor its position, GRBL 1.1 interface docs)."""
    return [(">>", b"?"), ("<<", recorded_replies(session)[b"?"][0])] + session


def recorded_replies(session: list[tuple[str, bytes]]) -> dict[bytes, list[bytes]]:
    """For every host chunk of a session, the firmware output that followed each occurrence."""
    out: dict[bytes, list[bytes]] = defaultdict(list)
    current = None
    for direction, data in session:
        if direction == ">>":
            current = data
            out[current].append(b"")
        elif direction == "<<" and current is not None:
            out[current][-1] += data
    return dict(out)


class ReplayPort:
    """A pyserial-like port replaying ``script`` (one session of :func:`read_trace`)."""

    def __init__(self, script: list[tuple[str, bytes]], answers: dict[bytes, list[bytes]] | None = None,
                 extras: dict[bytes, list[bytes]] | None = None, timeout: float = 0.01) -> None:
        self.script = [(d, b) for d, b in script if d in (">>", "<<") or (d, b) == DROP]
        self.answers = {k: list(v) for k, v in (answers or {}).items()}
        self.extras = {k: list(v) for k, v in (extras or {}).items()}
        self.port = "replay://"
        self.timeout = timeout
        self.sent: list[bytes] = []
        self.diverged_at: int | None = None
        self.dropped = False
        self._out = bytearray()
        self._cursor = 0
        self._release()

    def _release(self) -> None:
        while self._cursor < len(self.script) and self.script[self._cursor][0] != ">>":
            self.dropped = self.script[self._cursor] == DROP
            self._cursor += 1
            if self.dropped:
                return
            self._out += self.script[self._cursor - 1][1]

    def write(self, data: bytes) -> int:
        if self.dropped:
            raise SerialException("socket disconnected (the recorded connection was dropped)")
        data = bytes(data)
        self.sent.append(data)
        if self.diverged_at is None and self._cursor < len(self.script) and self.script[self._cursor][1] == data:
            self._cursor += 1
            self._release()
        elif data in self.extras:
            self._out += self.extras[data][-1]
        else:
            if self.diverged_at is None:
                self.diverged_at = len(self.sent) - 1
            if data in self.answers:
                queue = self.answers[data]
                self._out += queue.pop(0) if len(queue) > 1 else queue[0]
        return len(data)

    def since_divergence(self) -> list[bytes]:
        return [] if self.diverged_at is None else self.sent[self.diverged_at:]

    @property
    def in_waiting(self) -> int:
        return len(self._out)

    def read(self, size: int = 1) -> bytes:
        if not self._out:
            if self.dropped:
                raise SerialException("socket disconnected (the recorded connection was dropped)")
            time.sleep(self.timeout)
        data = bytes(self._out[:size])
        del self._out[:size]
        return data

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self._out.clear()

    def close(self) -> None:
        pass
