"""Replay (dipnet.monitor.replay): a recording written out again reading by reading, as a scan would be,
followed by the monitor like a live scan; the authors' CSV included."""

from __future__ import annotations

import time

import pytest

from dipnet.core.rawscan import read_rawscan
from dipnet.monitor.replay import Replay, load_recording
from dipnet.monitor.server import Monitor
from dipnet.preprocessing.datasets import data_path

AUTHORS_CSV = data_path("real/3cats_fixture_3mm.csv")


def test_a_replay_writes_every_reading_again(recorded_scan, tmp_path):
    target = tmp_path / "replay.jsonl"
    replay = Replay(recorded_scan, target, speed=float("inf")).start()
    assert replay.finished.wait(60)
    again, original = read_rawscan(target), read_rawscan(recorded_scan)
    assert [o.values.tolist() for o in again.orientations] == [o.values.tolist() for o in original.orientations]
    assert again.complete_orientations() == original.complete_orientations()


def test_a_replay_keeps_the_recorded_pace_divided_by_the_speed(recorded_scan, tmp_path):
    raw = read_rawscan(recorded_scan)
    recorded = raw.orientations[-1].time_s[-1] - raw.orientations[0].time_s[0]
    speed = recorded / 1.5                                           # the whole scan in about 1.5 s
    target = tmp_path / "replay.jsonl"
    start = time.monotonic()
    assert Replay(recorded_scan, target, speed=speed).start().finished.wait(60)
    assert time.monotonic() - start >= 1.4
    times = [t for o in read_rawscan(target).orientations for t in o.time_s]
    # the readings carry the wall-clock time of their writing: a loaded machine stretches the span (2.34 s beside
    # the other tests in CI), never shrinks it below the pace; at the recorded pace it would be 0.6 s
    assert 1.0 <= times[-1] - times[0] <= 4.5


def test_the_authors_csv_replays_with_its_plan(tmp_path):
    raw = load_recording(AUTHORS_CSV)
    assert len(raw.header.config["plan"]["orientations"]) == len(raw.orientations) == 32
    monitor = Monitor(tmp_path / "replay.jsonl", replay=True)
    replay = Replay(AUTHORS_CSV, tmp_path / "replay.jsonl", speed=float("inf")).start()
    assert replay.finished.wait(60)
    monitor.refresh()
    state = monitor.state
    assert state["mode"] == "replay" and state["timing"]["done"] == 32 and state["timing"]["planned"] == 32
    assert state["n_readings"] == sum(o.n_readings for o in raw.orientations)


def test_a_bad_speed_is_refused(recorded_scan, tmp_path):
    with pytest.raises(ValueError, match="replay speed must be positive"):
        Replay(recorded_scan, tmp_path / "r.jsonl", speed=0)
