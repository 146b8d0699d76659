"""The live monitor's costs, with the fake rig (not a timed test; docs/benchmarks/monitor.md).

1. **Slowdown**: the same fake-rig scan (``scripts/scan.py``, ``--dips`` orientations, ``--settle`` s
   per reading so that the scan waits on its rig as a real one does) run alternately without and with
   ``monitor=true`` (the monitor process with its running reconstruction), ``--repeats`` times each; the
   scan's own time is the span of its readings' times in the raw scan; slowdown = median with / median
   without - 1.
2. **Latency**: during every monitored run a client follows the page's event stream (what the page's
   JavaScript receives); a reading's latency is the time from its recorded time (written when it was
   taken) to the first event that holds it; the worst over all readings.
3. **Refresh**: the running reconstruction's update (:func:`dipnet.monitor.worker.reconstruct_scan`,
   what the worker process runs: read, ``minnorm`` solve, posterior uncertainty, mesh, predicted curves)
   at ``--resolution``^3 on the first 1/4, 1/2, 3/4 and all dips of the first monitored scan (``--quick``:
   1/2 and all), one torch thread; the worst.

Prints a table and ends with ``RESULT latency_s=<worst> refresh_s=<worst> slowdown=<relative>``.

    python scripts/bench_monitor.py --quick        # 6 dips, 2 runs each way, 48^3: under 3 minutes
    python scripts/bench_monitor.py                # 40 dips (the default scan), 3 runs each way
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from dipnet.experiments.bench_options import count_type, grid_size_type, number_type
from dipnet.experiments.quick_mode import apply_quick, given_options
from dipnet.jobs.cli import user_errors

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def follow_events(port: int, arrivals: list[tuple[float, int]], stop: threading.Event) -> None:
    """Record ``(receive time, readings in the state)`` of every ``state`` event of the monitor on ``port``."""
    import httpx

    while not stop.is_set():
        try:
            with httpx.stream("GET", f"http://127.0.0.1:{port}/api/events", timeout=None) as events:
                kind = None
                for line in events.iter_lines():
                    if line.startswith("event: "):
                        kind = line[len("event: "):]
                    elif line.startswith("data: ") and kind == "state":
                        arrivals.append((time.time(), int(json.loads(line[len("data: "):]).get("n_readings") or 0)))
                    if stop.is_set():
                        return
        except (httpx.HTTPError, OSError):
            time.sleep(0.2)  # the monitor is not up yet


def reading_times(path: Path) -> list[float]:
    """The recorded time (UNIX s) of every reading, in file order."""
    return [json.loads(line)["time_s"] for line in path.read_text().splitlines() if '"type": "reading"' in line]


def run_scan(run_dir: Path, args: argparse.Namespace, monitor: bool) -> dict:
    """One fake-rig scan; with ``monitor``, the worst reading-to-page latency too."""
    port = free_port()
    command = [sys.executable, str(ROOT / "scripts" / "scan.py"), f"hydra.run.dir={run_dir}", "progress=false",
               f"n_dips={args.dips}", f"protocol.step_mm={args.step}", f"protocol.settle_s={args.settle}",
               "sensor.device.timeout=10", f"monitor={'true' if monitor else 'false'}", f"monitor_port={port}"]
    arrivals: list[tuple[float, int]] = []
    stop = threading.Event()
    follower = threading.Thread(target=follow_events, args=(port, arrivals, stop), daemon=True)
    if monitor:
        follower.start()
    subprocess.run(command, check=True, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    stop.set()
    times = reading_times(run_dir / "rawscan.jsonl")
    out = {"scan_s": times[-1] - times[0], "readings": len(times)}
    if monitor:
        # readings taken before the first event (the monitor still starting) are left out: the page was not up
        first = arrivals[0] if arrivals else (float("inf"), 0)
        latencies = []
        for j, t in enumerate(times):
            if j < first[1] or t < first[0]:
                continue
            shown = next((at for at, n in arrivals if n > j), None)
            latencies.append(float("inf") if shown is None else shown - t)
        out.update(latency_s=max(latencies) if latencies else float("nan"), followed=len(latencies))
    return out


def refresh_times(scan: Path, resolution: int, fractions: tuple[float, ...]) -> list[tuple[int, float]]:
    """``(dips, seconds)`` of the reconstruction update on the first ``fractions`` of the dips of ``scan``."""
    import torch

    from dipnet.monitor.worker import reconstruct_scan

    torch.set_num_threads(1)
    lines = scan.read_text().splitlines(keepends=True)
    ends = [i for i, line in enumerate(lines) if '"type": "complete"' in line]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for fraction in fractions:
            end = ends[max(int(round(fraction * len(ends))) - 1, 0)]
            part = Path(tmp) / "rawscan.jsonl"
            part.write_text("".join(lines[: end + 1]))
            start = time.perf_counter()
            result = reconstruct_scan(part, resolution)
            out.append((result["n_dips"], time.perf_counter() - start))
    return out


def parse_args(argv=None) -> argparse.Namespace:
    """The options, each refused before any scan when no run could use it (one line naming it, exit 2): ``--dips``,
    ``--repeats`` (``0`` ran no scan and ended in a traceback), ``--step``,
    ``--settle``, ``--resolution``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="6 dips of 28 readings, 2 runs each way, 2 updates timed")
    p.add_argument("--dips", type=count_type(1, "dips"), default=40)
    p.add_argument("--step", type=number_type("mm", above=0), default=2.0, help="lowering step (mm)")
    p.add_argument("--settle", type=number_type("seconds", at_least=0), default=0.1,
                   help="wait before each reading (s): the rig's pace")
    p.add_argument("--repeats", type=count_type(1, "runs each way"), default=3,
                   help="runs with and without the monitor")
    p.add_argument("--resolution", type=grid_size_type(3), default=48)
    args = p.parse_args(argv)
    if args.quick:  # the options given beside --quick keep their values
        apply_quick(args, given_options(p, argv), dips=6, step=4.0, repeats=2)
    return args


def main(argv=None) -> None:
    """Run the benchmark; a bad option: one line ``error: ...`` and exit 2, before any scan."""
    with user_errors():
        run(argv)


def run(argv=None) -> None:
    args = parse_args(argv)
    fractions = (0.5, 1.0) if args.quick else (0.25, 0.5, 0.75, 1.0)
    runs = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for monitor in (False, True):
                run_dir = Path(tmp) / f"{'on' if monitor else 'off'}{r}"
                result = run_scan(run_dir, args, monitor)
                runs[monitor].append(result)
                print(f"run {r} monitor={'on ' if monitor else 'off'}: scan {result['scan_s']:7.2f} s, "
                      f"{result['readings']} readings" + (f", worst latency {result['latency_s']:.3f} s over "
                                                          f"{result['followed']} readings" if monitor else ""),
                      flush=True)
        refresh = refresh_times(Path(tmp) / "on0" / "rawscan.jsonl", args.resolution, fractions)
        shutil.rmtree(tmp, ignore_errors=True)
    off = statistics.median(r["scan_s"] for r in runs[False])
    on = statistics.median(r["scan_s"] for r in runs[True])
    latency = max(r["latency_s"] for r in runs[True])
    worst_refresh = max(s for _, s in refresh)
    print()
    print("| measure | value | target |")
    print("|---|---|---|")
    print(f"| scan time without the monitor (median of {args.repeats}) | {off:.2f} s | |")
    print(f"| scan time with the monitor (median of {args.repeats}) | {on:.2f} s | |")
    print(f"| slowdown | {on / off - 1:+.3f} | < 0.05 |")
    print(f"| reading to page, worst | {latency:.3f} s | < 2 s |")
    for dips, seconds in refresh:
        print(f"| reconstruction update at {args.resolution}^3, {dips} dips | {seconds:.2f} s | < 20 s |")
    print(f"RESULT latency_s={latency:.3f} refresh_s={worst_refresh:.2f} slowdown={on / off - 1:.4f}")


if __name__ == "__main__":
    main()
