"""What the monitor page shows (dipnet.monitor.state): the mode and its message for a scan that runs,
finished, stopped or died; the finish time; the warnings the readings raise; the predicted trace."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import numpy as np
import pytest

from dipnet.core.rawscan import ScanHeader
from dipnet.core.rawscan_writer import RawScanWriter
from dipnet.monitor.state import finish_estimate, predicted_trace, snapshot, writer_alive
from dipnet.monitor.tail import Dip, JournalTail, ScanTail, journal_path

PLAN = {"orientations": [[10.0, 0.0], [20.0, 90.0], [30.0, 180.0], [40.0, 270.0]],
        "start_mm": 0.0, "stop_mm": 4.0, "step_mm": 1.0}


def synthetic_scan(path: Path, levels: list[list[float]], complete: int, starts=(0.0, 10.0, 20.0)) -> Path:
    """A scan of :data:`PLAN` (5 readings per dip, 1 s apart; dip k starts at ``starts[k]`` s), the first
    ``complete`` dips complete."""
    header = ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0, resolution=0.001, config={"plan": PLAN})
    with RawScanWriter(path, header, resume=False, fsync=False) as writer:
        for k, values in enumerate(levels):
            writer.begin_orientation(k, tilt_deg=PLAN["orientations"][k][0], spin_deg=PLAN["orientations"][k][1])
            for i, value in enumerate(values):
                writer.append_reading(float(i), value, starts[k] + i, [])
            if k < complete:
                writer.complete_orientation()
    return path


def _state(path: Path, **options) -> dict:
    tail, journal = ScanTail(path), JournalTail(path)
    tail.poll()
    journal.poll()
    return snapshot(tail, journal, **options)


RISING = [100.0, 100.0, 100.5, 101.0, 101.5]


def test_a_finished_scan_says_finished(recorded_scan):
    state = _state(recorded_scan)
    assert state["mode"] == "finished" and state["message"] == "finished: 6 of 6 orientations recorded"
    assert {o["status"] for o in state["orientations"]} == {"done"} and state["stopped"] is None
    json.dumps(state)                                              # what the page receives


def test_a_running_scan_is_live_with_its_dip_in_progress_and_the_rest_planned(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING, RISING[:2]], complete=2)
    holder = tmp_path / ".rawscan.jsonl.lock.holder"               # what a running scan's lock leaves
    holder.write_text(f"pid {os.getpid()} on {socket.gethostname()}, since now\n")
    assert writer_alive(path)
    state = _state(path, alive=True, now=21.0)
    assert state["mode"] == "live" and "2 of 4 orientations done" in state["message"]
    assert [o["status"] for o in state["orientations"]] == ["done", "done", "in progress", "planned"]
    assert state["dip"]["k"] == 2 and state["dip"]["values"] == RISING[:2] and state["dip"]["n_planned"] == 5
    assert state["stage_mm"] == 1.0


def test_the_finish_time_counts_the_readings_left_and_the_dips_left(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING, RISING[:2]], complete=2)
    tail = ScanTail(path)
    tail.poll()
    timing = finish_estimate(tail, now=21.0)
    # 10 s per dip, 1 s per reading: this dip's last reading at 24 s, the next dip starts at 30 s, ends at 40 s
    assert timing["per_dip_s"] == pytest.approx(10.0) and timing["per_reading_s"] == pytest.approx(1.0)
    assert timing["finish_time"] == pytest.approx(40.0) and timing["remaining_s"] == pytest.approx(19.0)


def test_a_dead_holder_or_none_means_not_running(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)
    assert not writer_alive(path)
    (tmp_path / ".rawscan.jsonl.lock.holder").write_text(f"pid {2**22 + 12345} on {socket.gethostname()}, since x\n")
    assert not writer_alive(path)                                  # a pid that does not exist: the scan died


def test_a_scan_that_died_says_so_and_how_to_resume(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)
    with path.open("ab") as f:
        f.write(b'{"type": "reading", "k": 1, "sta')                # killed mid-line
    state = _state(path)
    assert state["mode"] == "stopped" and state["stopped"] == state["message"]
    assert "it left no safe-stop message (in its monitor journal or in scan.log beside it), so it died" in \
        state["message"] and "last line is cut short" in state["message"]
    assert "1 of 4 orientations done" in state["message"] and "run the same scan command again" in state["message"]
    assert [o["status"] for o in state["orientations"]] == ["done", "incomplete", "planned", "planned"]


def test_a_safe_stop_shows_its_message_until_a_new_run_starts(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)
    message = "scan stopped at orientation 1: RigTimeout: ...; object lifted: ...; run the same command again"
    records = [{"type": "session", "time": 1.0}, {"type": "error", "message": message, "logger": "dipnet", "time": 2.0},
               {"type": "stopped", "message": message, "time": 2.0}]
    journal_path(path).write_text("".join(json.dumps(r) + "\n" for r in records))
    state = _state(path)
    assert state["mode"] == "stopped" and state["message"] == message == state["stopped"]
    assert not any(message in w for w in state["warnings"])       # said once, as the stop
    with journal_path(path).open("a") as f:                         # resumed: the new run is live
        f.write(json.dumps({"type": "session", "time": 3.0}) + "\n")
    assert _state(path, alive=True)["mode"] == "live"


def test_a_safe_stop_logged_beside_a_scan_without_a_journal_is_shown(tmp_path):
    """A scan run without monitor=true keeps no journal; scan.py logs its safe stop to scan.log beside the scan. The
    monitor called such a Ctrl-C'd scan dead ("killed, crashed or lost power: check the rig"). A stop logged before
    the scan's last session began is an earlier run's: that run resumed, and then died."""
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)
    stop = ("scan stopped at orientation 1 (tilt 20, spin 90), reading 3 at 3 mm: interrupted (Ctrl-C); object lifted: "
            "...; run the same command again to resume")
    (tmp_path / "scan.log").write_text(f"[2026-11-27 19:24:20,100][dipnet][INFO] - orientation 1\n"
                                       f"[2026-11-27 19:24:26,794][dipnet][ERROR] - error: {stop}\n")
    state = _state(path)
    assert state["mode"] == "stopped" and state["message"] == stop
    with path.open("a") as f:  # resumed an hour later (the runner's session record), then killed
        f.write(json.dumps({"type": "session", "first_k": 1, "time": "2026-11-27T20:30:00+0000"}) + "\n")
    state = _state(path)
    assert state["mode"] == "stopped" and "so it died" in state["message"]


def test_an_adaptive_scan_counts_its_budget_not_its_first_batch(tmp_path):
    """An adaptive scan's header lists only its first batch (4 of a budget of 12): cut off after that batch it was
    shown "finished: 4 of 4 orientations recorded", and complete it would read "12 of 4"."""
    path = tmp_path / "rawscan.jsonl"
    config = {"plan": PLAN, "scan": {"planner": {"_target_": "dipnet.planning.plans.AdaptivePlan", "budget": 12,
                                                 "batch_size": 4}}}
    header = ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0, resolution=0.001, config=config)
    with RawScanWriter(path, header, resume=False, fsync=False) as writer:
        for k in range(4):
            writer.begin_orientation(k, tilt_deg=PLAN["orientations"][k][0], spin_deg=PLAN["orientations"][k][1])
            for i, value in enumerate(RISING):
                writer.append_reading(float(i), value, 10.0 * k + i, [])
            writer.complete_orientation()
    state = _state(path)
    assert state["mode"] == "stopped" and "4 of 12 orientations done" in state["message"]
    tail = ScanTail(path)
    tail.poll()
    assert finish_estimate(tail, now=100.0)["planned"] == 12
    # its uncertainty stop after 4 dips: scan.py logs "scan complete" (it was called dead); a Ctrl-C while it
    # planned the next batch logs one line (it was called dead too)
    log = tmp_path / "scan.log"
    log.write_text("[2026-11-27 19:30:00,000][dipnet][INFO] - scan complete: 4 orientations, 20 readings in x\n")
    state = _state(path)
    assert state["mode"] == "finished" \
        and state["message"] == "finished: scan complete: 4 orientations, 20 readings in x"
    stop = "scan stopped outside a dip (no dip was in progress): every complete dip is kept in x; run the same command"
    log.write_text(f"[2026-11-27 19:30:00,000][dipnet][ERROR] - interrupted: {stop}\n")
    assert _state(path)["message"] == stop


def test_a_damaged_line_is_named_not_taken_for_a_crash(tmp_path):
    """A finished scan with one damaged line in the middle was shown as died ("check the rig ... resume"); resuming
    cannot mend the file."""
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING, RISING], complete=3)
    lines = path.read_text().splitlines(keepends=True)
    lines.insert(len(lines) // 2, "garbage that is not JSON\n")
    path.write_text("".join(lines))
    state = _state(path)
    assert state["mode"] == "stopped" and state["message"].startswith("the scan file cannot be read past ")
    assert "a damaged line, which resuming does not mend" in state["message"] and "died" not in state["message"]


def test_a_replay_says_replay(recorded_scan):
    state = _state(recorded_scan, replay=True)
    assert state["mode"] == "replay" and state["message"].startswith("replay of a recorded scan")


def test_a_file_without_its_header_yet_says_so(tmp_path):
    path = tmp_path / "rawscan.jsonl"
    path.write_text("")
    state = _state(path, alive=True)
    assert state["mode"] == "live" and "no header line yet" in state["message"]


def test_a_falling_level_and_a_drifting_rest_level_are_warnings(tmp_path):
    leaking = [100.0, 100.0, 100.5, 100.2, 101.0]                  # fell 0.3 mm at stage 3
    drifted = [x + 0.8 for x in RISING]
    state = _state(synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, leaking, drifted], complete=3))
    text = "\n".join(state["warnings"])
    assert "orientation 1: the level fell by 0.3 mm while the object went down (at 3 mm)" in text
    assert "orientation 2: the resting level is +0.8 mm from the first dip's" in text
    assert "orientation 0" not in text


def test_the_predicted_trace_solves_the_tank_balance():
    # a prism of section c (mm^2) from height b up: C(t) = c (t - b); A delta = C(t0 + s + delta)
    area, c, b, t0 = 1e4, 2e3, -5.0, -8.0
    edges = np.linspace(-50, 50, 101)
    recon = {"edges": edges.tolist(), "cumulative": {"10.000000,20.000000": np.clip(c * (edges - b), 0, None).tolist()}}
    stages = np.arange(0.0, 20.0, 2.0)
    dip = Dip(0, 10.0, 20.0, None, {"t_start_mm": t0}, stages.tolist(), [150.0] * len(stages))
    predicted = np.asarray(predicted_trace(recon, dip, area))
    rise = np.clip(c * (t0 + stages - b) / (area - c), 0, None)      # the fixed point, in closed form
    np.testing.assert_allclose(predicted, 150.0 + rise, atol=1e-6)
    assert predicted_trace(recon, Dip(0, 10.0, 20.0, None, {}, [0.0], [1.0]), area) is None   # no start height
    assert predicted_trace(None, dip, area) is None


def test_a_resumed_scan_shows_what_was_recorded_before_and_goes_on(tmp_path):
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)   # stopped in dip 1
    tail, journal = ScanTail(path), JournalTail(path)
    tail.poll()
    assert [len(d.values) for d in tail.dips] == [5, 3]
    header = ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0, resolution=0.001, config={"plan": PLAN})
    with RawScanWriter(path, header, resume=True, fsync=False) as writer:   # the resumed run redoes dip 1
        writer.record_session({"first_k": 1})
        writer.begin_orientation(1, tilt_deg=20.0, spin_deg=90.0)
        writer.append_reading(0.0, 100.0, 30.0, [])
    tail.poll()
    state = snapshot(tail, journal, alive=True, now=31.0)
    assert [len(d.values) for d in tail.dips] == [5, 1] and state["sessions"] == 1
    assert [o["status"] for o in state["orientations"]] == ["done", "in progress", "planned", "planned"]


def test_a_scan_whose_orientations_give_only_a_direction_is_shown(tmp_path):
    """A raw scan may give an orientation's direction without rig angles (the format allows it, the reconstruction
    reads it): the page's state crashed formatting the missing tilt (TypeError), and so did a replay of such a file,
    whose plan then listed no angles."""
    path = tmp_path / "rawscan.jsonl"
    plan = {"orientations": [[None, None]] * 3}
    header = ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0, resolution=0.001, config={"plan": plan})
    directions = [[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.6, 0.0, 0.8]]
    with RawScanWriter(path, header, resume=False, fsync=False) as writer:
        for k in range(2):
            writer.begin_orientation(k, direction=directions[k], meta={"t_start_mm": -5.0})
            for i, value in enumerate(RISING[:5 - 2 * k]):
                writer.append_reading(float(i), value, 10.0 * k + i, [])
            if k == 0:
                writer.complete_orientation()
    recon = {"edges": [-50.0, 50.0], "cumulative": {}}
    tail, journal = ScanTail(path), JournalTail(path)
    tail.poll()
    state = snapshot(tail, journal, alive=True, recon=recon)
    assert state["mode"] == "live" and "1 of 3 orientations done" in state["message"]
    assert state["where"].startswith("orientation 1 (direction [0, 0.6, 0.8])") and state["dip"]["predicted"] is None
    assert [o["direction"] for o in state["orientations"]] == directions[:2]
    json.dumps(state)


def test_a_stop_journalled_by_an_earlier_run_is_not_shown_after_a_resume_without_the_monitor(tmp_path):
    """A run with monitor=true stopped (its journal holds the stop); the scan was resumed without monitor=true (no
    journal session) and finished: the page kept showing the old stop."""
    path = synthetic_scan(tmp_path / "rawscan.jsonl", [RISING, RISING[:3]], complete=1)
    message = "scan stopped at orientation 1: RigTimeout: ...; object lifted: ...; run the same command again"
    records = [{"type": "session", "time": 1.7e9}, {"type": "stopped", "message": message, "time": 1.7e9 + 60}]
    journal_path(path).write_text("".join(json.dumps(r) + "\n" for r in records))
    assert _state(path)["message"] == message
    header = ScanHeader(tank_cross_section_mm2=1e4, step_mm=1.0, resolution=0.001, config={"plan": PLAN})
    with RawScanWriter(path, header, resume=True, fsync=False) as writer:   # resumed an hour later, to the end
        writer.record_session({"first_k": 1, "time": "2023-11-14T23:13:20+0000"})   # 1.7e9 + 3600 s
        for k in (1, 2, 3):
            writer.begin_orientation(k, tilt_deg=PLAN["orientations"][k][0], spin_deg=PLAN["orientations"][k][1])
            for i, value in enumerate(RISING):
                writer.append_reading(float(i), value, 1.7e9 + 3600 + 10 * k + i, [])
            writer.complete_orientation()
    state = _state(path)
    assert state["mode"] == "finished" and state["message"] == "finished: 4 of 4 orientations recorded"


def test_a_balance_scan_predicts_its_reading_in_grams():
    """A balance's reading rises by the displaced water's mass (density x A x rise), not by the level's rise in mm:
    the page drew a balance scan's predicted trace about A x density times too flat."""
    area, c, b, t0, density = 1e4, 2e3, -5.0, -8.0, 1e-3
    edges = np.linspace(-50, 50, 101)
    recon = {"edges": edges.tolist(), "cumulative": {"10.000000,20.000000": np.clip(c * (edges - b), 0, None).tolist()}}
    stages = np.arange(0.0, 20.0, 2.0)
    dip = Dip(0, 10.0, 20.0, None, {"t_start_mm": t0}, stages.tolist(), [0.0] * len(stages))
    level = np.asarray(predicted_trace(recon, dip, area))
    mass = np.asarray(predicted_trace(recon, dip, area, density))
    np.testing.assert_allclose(mass, density * area * level)
    volume = np.interp(t0 + stages + level, edges, recon["cumulative"]["10.000000,20.000000"])
    np.testing.assert_allclose(mass, density * volume, rtol=1e-6)   # the displaced water's mass


def test_a_balance_scan_state_carries_its_density_to_the_trace(tmp_path):
    path = tmp_path / "rawscan.jsonl"
    header = ScanHeader(quantity="mass_g", tank_cross_section_mm2=1e4, step_mm=1.0, config={"plan": PLAN})
    with RawScanWriter(path, header, resume=False, fsync=False) as writer:
        writer.begin_orientation(0, tilt_deg=10.0, spin_deg=0.0, meta={"t_start_mm": -3.0})
        for i in range(5):
            writer.append_reading(float(i), 0.0, float(i), [])
    edges = np.linspace(-50, 50, 101)
    recon = {"edges": edges.tolist(), "cumulative": {"10.000000,0.000000": np.clip(500.0 * edges, 0, None).tolist()}}
    tail, journal = ScanTail(path), JournalTail(path)
    tail.poll()
    predicted = snapshot(tail, journal, alive=True, recon=recon)["dip"]["predicted"]
    dip = tail.dips[0]
    level = np.asarray(predicted_trace(recon, dip, 1e4))
    assert level[-1] > level[0]
    np.testing.assert_allclose(predicted, header.density_g_per_mm3 * 1e4 * level)   # grams, not the mm of a level
