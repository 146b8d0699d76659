"""One end of a link to the fake world (dipnet.rig.fake.device): replies in order at their time, real-time output
overtaking them, input split into lines, G-code words."""

from __future__ import annotations

import time

from dipnet.rig.fake.device import Device, parse_words

from fake_talk import ball_world, replies


class Echo(Device):
    """Answers every input line with ``echo <line>``."""

    def parse_input(self) -> None:
        for line in self.lines():
            self.emit(f"echo {line}")


def test_g_code_words_are_read_by_letter():
    assert parse_words("G1 Z-20.5 a+3 F500") == {"G": 1.0, "Z": -20.5, "A": 3.0, "F": 500.0}
    assert parse_words("G0 X.25 Y-0.5") == {"G": 0.0, "X": 0.25, "Y": -0.5}
    assert parse_words("M400") == {"M": 400.0} and parse_words("") == {}


def test_input_is_split_into_lines_whatever_the_chunks():
    dev = Echo(ball_world())
    dev.receive(b"fir")
    assert dev.take(100, 0.0) == b""  # half a line: nothing to answer yet
    dev.receive(b"st\r\nsecond\nthi")
    assert replies(dev) == ["echo first", "echo second"]
    assert replies(dev, b"rd\n") == ["echo third"]


def test_replies_keep_their_order_and_real_time_output_overtakes_them():
    """A reply scheduled late holds back the replies after it (a firmware answers lines in order); a status
    report (real time) is not held back."""
    dev = Echo(ball_world())
    dev.emit("ok late", at=time.monotonic() + 0.15)
    dev.emit("ok next")
    dev.emit("<Idle>", realtime=True)
    assert dev.take(100, 0.05) == b"<Idle>\r\n"
    assert dev.take(100, 0.05) == b""  # 'ok next' waits for 'ok late'
    assert replies(dev, timeout=0.3) == ["ok late", "ok next"]


def test_reads_return_at_most_size_bytes_and_the_rest_stays_queued():
    dev = Echo(ball_world())
    dev.emit("abcdef")
    assert dev.pending() == 8
    assert dev.take(4, 0.0) == b"abcd" and dev.pending() == 4
    assert dev.take(100, 0.0) == b"ef\r\n" and dev.pending() == 0
    dev.emit("gone")
    dev.clear_output()
    assert dev.take(100, 0.0) == b""


def test_the_world_latency_delays_every_reply():
    dev = Echo(ball_world(latency_s=0.1))
    start = time.monotonic()
    assert replies(dev, "ping", timeout=0.3) == ["echo ping"]
    assert time.monotonic() - start >= 0.1 - 0.005
