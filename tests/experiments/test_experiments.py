"""Collecting, aggregating, tabulating and plotting sweeps (dipnet.experiments, scripts/compare.py),
on a synthetic sweep directory whose metrics follow known formulas."""

from __future__ import annotations

import csv
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from dipnet.experiments import collect, figures, tables
from dipnet.jobs import sweep_jobs
from dipnet.core.grid import Grid
from sweep_fixtures import ball, write_job
from script_modules import load_script

ROOT = Path(__file__).resolve().parents[2]
SOLVERS, DIPS, SEEDS, SNRS = ("minnorm", "lsmr"), (4, 8, 16), (0, 1), (10.0, 20.0, 30.0)


def iou_of(solver: str, n_dips: int, seed: int) -> float:
    return 1 - 1 / n_dips - 0.01 * seed + (0.02 if solver == "lsmr" else 0.0)


def chamfer_of(n_dips: int, seed: int) -> float:
    return 0.1 / n_dips + 0.001 * seed


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    """12 noise-free jobs (2 solvers x 3 budgets x 2 seeds), 3 noisy ones, a failed one, a
    partial one (config only) and an empty numbered directory."""
    root = tmp_path_factory.mktemp("sweep")
    (root / "multirun.yaml").write_text("hydra: {}\n")
    num = 0
    for solver in SOLVERS:
        for n in DIPS:
            for seed in SEEDS:
                write_job(root / str(num), solver=solver, n_dips=n, snr_db=None, seed=seed,
                          metrics={"iou": iou_of(solver, n, seed), "chamfer": chamfer_of(n, seed),
                                   "false_positive": 0.0, "false_negative": 0.0})
                num += 1
    for snr in SNRS:
        write_job(root / str(num), solver="minnorm", n_dips=8, snr_db=snr, seed=0,
                  metrics={"iou": iou_of("minnorm", 8, 0) - 1 / snr, "chamfer": chamfer_of(8, 0),
                           "false_positive": 1 / snr, "false_negative": 0.5 / snr})
        num += 1
    write_job(root / str(num), solver="lsmr", n_dips=32, snr_db=None, seed=0, metrics=None,
              error="ValueError: n_dips too large for the test")
    write_job(root / str(num + 1), solver="lsmr", n_dips=64, snr_db=None, seed=0, metrics=None)
    (root / str(num + 2)).mkdir()
    return root


def test_collect_finds_every_job_with_its_status(sweep):
    runs = collect.collect_runs(sweep)
    assert len(runs) == len(SOLVERS) * len(DIPS) * len(SEEDS) + len(SNRS) + 3
    assert [r.path.name for r in runs] == [str(i) for i in range(len(runs))]     # natural order, not 1, 10, 11
    status = {r.path.name: r.status for r in runs}
    n = len(runs)
    assert (status[str(n - 3)], status[str(n - 2)], status[str(n - 1)]) == ("failed", "unfinished", "unfinished")
    assert sum(s == "ok" for s in status.values()) == n - 3
    failed = runs[n - 3]
    assert failed.error == "ValueError: n_dips too large for the test"
    assert collect.problems(runs) == runs[n - 3:]


def test_a_single_job_dir_and_a_corrupt_metrics_file(tmp_path):
    job = write_job(tmp_path / "job", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.5})
    assert [r.status for r in collect.collect_runs(job)] == ["ok"]
    (job / "metrics.json").write_text("{not json")
    run = collect.load_run(job)
    assert run.status == "failed" and "metrics.json" in run.error


def test_no_runs_is_a_clear_error(tmp_path):
    (tmp_path / "notes").mkdir()
    with pytest.raises(collect.NoRunsError, match="no reconstruction jobs found"):
        collect.collect_runs(tmp_path)
    with pytest.raises(collect.NoRunsError, match="not a directory"):
        collect.collect_runs(tmp_path / "missing")


def test_rows_carry_the_sweep_axes(sweep):
    runs = collect.collect_runs(sweep)
    rows = collect.run_rows(runs, sweep)
    first = rows[0]
    assert first["job"] == "0" and first["solver"] == "minnorm" and first["shape"] == "disk"
    assert first["n_dips"] == 4 and first["snr_db"] is None and first["seed"] == 0
    # 2D, N = M = 16: a square system needs N^2 / M = 16 dips, so 4 dips are 25 %.
    assert first["dips_percent"] == pytest.approx(25.0)
    assert first["iou"] == pytest.approx(iou_of("minnorm", 4, 0))
    noisy = [r for r in rows if r["snr_db"] is not None]
    assert sorted(r["snr_db"] for r in noisy) == list(SNRS)
    partial = rows[-2]          # config only: the axes still come from .hydra/config.yaml
    assert (partial["status"], partial["solver"], partial["n_dips"]) == ("unfinished", "lsmr", 64)
    assert collect.dips_percent(41, 64, 3) == pytest.approx(100 * 41 / 64 ** 2)


def test_swept_options_become_columns():
    values = collect.override_values(["+experiment=dips_sweep", "solver.priors.tv.weight=0.01", "n_dips=5",
                                          "snr_db=null", "~output.figures", "hydra.launcher.n_jobs=2"])
    assert values == {"experiment": "dips_sweep", "solver.priors.tv.weight": 0.01, "n_dips": 5, "snr_db": None}
    run = collect.Run(Path("job"), "ok", overrides=["solver.priors.tv.weight=0.01", "n_dips=5"],
                          metrics={"n_dips": 7})
    row = collect.run_row(run)
    assert row["solver.priors.tv.weight"] == 0.01 and row["n_dips"] == 7      # metrics win over overrides


def test_aggregate_mean_and_spread(sweep):
    rows = collect.run_rows(collect.collect_runs(sweep))
    groups = collect.aggregate(rows)
    assert len(groups) == len(SOLVERS) * len(DIPS) + len(SNRS)       # failed/unfinished ignored
    by_key = {(g["solver"], g["n_dips"], g["snr_db"]): g for g in groups}
    for solver in SOLVERS:
        for n in DIPS:
            g = by_key[(solver, n, None)]
            values = [iou_of(solver, n, s) for s in SEEDS]
            assert g["runs"] == len(SEEDS)
            assert g["iou_mean"] == pytest.approx(np.mean(values))
            assert g["iou_std"] == pytest.approx(np.std(values, ddof=1))
            assert g["chamfer_mean"] == pytest.approx(np.mean([chamfer_of(n, s) for s in SEEDS]))
    single = by_key[("minnorm", 8, 20.0)]
    assert single["runs"] == 1 and single["iou_std"] == 0.0
    assert single["false_positive_mean"] == pytest.approx(1 / 20)
    assert "hausdorff_mean" not in single                             # absent metric stays absent
    keys = [(g["solver"], g["n_dips"]) for g in groups]
    assert keys == sorted(keys)                                       # sorted by the group keys
    # None (noise-free) sorts after the noise levels of the same solver and budget
    assert [g["snr_db"] for g in groups if (g["solver"], g["n_dips"]) == ("minnorm", 8)] == [*SNRS, None]


def test_aggregate_skips_non_finite_values():
    rows = [{"status": "ok", "solver": "a", "iou": v} for v in (0.5, float("nan"), 0.7)]
    (g,) = collect.aggregate(rows, by=("solver",), metrics=("iou",))
    assert g["runs"] == 3 and g["iou_mean"] == pytest.approx(0.6)


def test_csv_and_markdown(sweep, tmp_path):
    runs = collect.collect_runs(sweep)
    rows = collect.run_rows(runs, sweep)
    path = tables.write_csv(rows, tmp_path / "runs.csv")
    with path.open() as f:
        read = list(csv.DictReader(f))
    assert len(read) == len(runs)
    assert read[-3]["status"] == "failed" and read[-3]["error"].startswith("ValueError")
    assert float(read[0]["iou"]) == pytest.approx(rows[0]["iou"])
    assert read[0]["snr_db"] == ""                                    # None -> empty cell

    groups = collect.aggregate(rows)
    table = tables.markdown_table(groups).splitlines()
    assert len(table) == 2 + len(groups)
    header = [c.strip() for c in table[0].strip("|").split("|")]
    assert header[:4] == ["solver", "dips", "SNR (dB)", "runs"] and "IoU" in header and "Hausdorff" not in header
    g = groups[0]
    cells = [c.strip() for c in table[2].strip("|").split("|")]
    assert cells[header.index("IoU")] == f"{g['iou_mean']:.3g} ± {g['iou_std']:.3g}"

    listing = tables.markdown_problems(runs, sweep)
    assert f"({3} of {len(runs)})" in listing and "ValueError: n_dips too large" in listing
    assert "unfinished" in listing and "solver=lsmr n_dips=64" in listing
    assert tables.markdown_problems(runs[:2]) == ""


def test_label_series_adds_noise_only_when_it_varies():
    rows = [{"status": "ok", "solver": "a", "snr_db": None}, {"status": "ok", "solver": "a", "snr_db": 30.0}]
    assert [r["series"] for r in collect.label_series(rows)] == ["a @ no noise", "a @ 30 dB"]
    assert [r["series"] for r in collect.label_series(rows[:1])] == ["a"]


def _is_png(path: Path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plots(sweep, tmp_path):
    runs = collect.collect_runs(sweep)
    rows = collect.run_rows(runs)
    assert _is_png(figures.plot_vs_dips(collect.aggregate(rows, ("solver", "n_dips")), tmp_path / "d.png"))
    assert _is_png(figures.plot_vs_dips(collect.aggregate(rows, ("solver", "dips_percent")),
                                            tmp_path / "p.png", x="dips_percent"))
    assert _is_png(figures.plot_vs_snr(collect.aggregate(rows, ("solver", "snr_db")), tmp_path / "s.png"))
    with pytest.raises(ValueError, match="snr_db"):
        figures.plot_vs_snr(collect.aggregate(rows[:2], ("solver", "snr_db")), tmp_path / "x.png")
    with pytest.raises(ValueError, match="metrics"):
        figures.plot_vs_dips(collect.aggregate(rows, ("solver", "n_dips"), metrics=()), tmp_path / "y.png")
    cells = figures.pick_montage(runs)
    assert set(cells) == {(s, n) for s in SOLVERS for n in DIPS}
    # the noise-free, lowest-seed run represents each cell
    assert all(c.metrics["snr_db"] is None and c.config["seed"] == 0 for c in cells.values())
    assert _is_png(figures.plot_montage(runs, tmp_path / "m.png"))
    rows_of = {k[0] for k in figures.pick_montage(runs, ("shape", "solver"))}
    assert rows_of == {f"disk / {s}" for s in SOLVERS}
    assert figures.varying(rows) == ["solver"]                    # one shape: rows by solver
    with pytest.raises(ValueError, match="no finished run"):
        figures.plot_montage(runs[-3:], tmp_path / "none.png")


def test_render_volume_shows_the_front_of_a_ball():
    grid = Grid(24, 3, 100.0)
    vol = ball(grid, 30.0)
    image = figures.render_volume(vol)
    assert image.shape == (24, 24)
    silhouette = vol.any(axis=1)[::-1]                                # seen along y, z up
    np.testing.assert_array_equal(image > 0, silhouette)
    centre = image[10:14, 10:14].mean()
    yy, xx = np.mgrid[:24, :24] - 11.5
    rim = image[(image > 0) & (np.hypot(yy, xx) > 5)].mean()
    assert centre > rim                                               # nearer (and facing) = brighter
    image2d = figures.render_volume(vol[12])
    np.testing.assert_array_equal(image2d, vol[12][::-1].astype(float))


def test_guarded_job_records_failures(tmp_path, caplog):
    assert sweep_jobs.guarded_job(lambda: 0.25, tmp_path / "ok") == 0.25
    assert not (tmp_path / "ok" / "error.txt").exists()

    def boom():
        raise ValueError("resolution must be at least 4 voxels")

    with caplog.at_level(logging.ERROR, logger="dipnet.jobs.sweep_jobs"):
        assert sweep_jobs.guarded_job(boom, tmp_path / "bad") is None
    text = (tmp_path / "bad" / "error.txt").read_text()
    assert text.splitlines()[0] == "ValueError: resolution must be at least 4 voxels"
    assert "Traceback" in text and "boom" in text
    assert "job failed: ValueError" in caplog.text
    assert collect.load_run(tmp_path / "bad").status == "failed"

    def cli_exit():
        raise SystemExit(2)

    assert sweep_jobs.guarded_job(cli_exit, tmp_path / "exit") is None
    assert (tmp_path / "exit" / "error.txt").read_text().startswith("SystemExit: 2")

    def interrupted():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep_jobs.guarded_job(interrupted, tmp_path / "stop")


def _hydra_cfg(out: Path, num: int, sweep_dir: Path | None = None):
    return OmegaConf.create({"hydra": {"runtime": {"output_dir": str(out)}, "job": {"num": num},
                                       "sweep": {"dir": str(sweep_dir or out.parent)}}})


def test_callback_logs_one_line_per_job_and_the_failures(sweep, tmp_path, caplog):
    callback = sweep_jobs.JobLogCallback()
    ok = JobReturn(overrides=["solver=minnorm", "n_dips=4"], status=JobStatus.COMPLETED)
    ok.return_value = 0.1
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"):
        callback.on_job_end(_hydra_cfg(sweep / "0", 0), ok)
    line = caplog.records[-1].getMessage()
    assert line.startswith("job 0 done [solver=minnorm n_dips=4]: IoU ")
    assert f"Chamfer {chamfer_of(4, 0):.4f}" in line and len(line) < 200   # the headline numbers only

    out = tmp_path / "crashed"
    out.mkdir()
    failed = JobReturn(overrides=["n_dips=-1"], status=JobStatus.FAILED)
    failed.return_value = RuntimeError("solver diverged")
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"):
        callback.on_job_end(_hydra_cfg(out, 7), failed)
    assert "job 7 FAILED [n_dips=-1]: solver diverged" in caplog.text
    assert (out / "error.txt").read_text().startswith("RuntimeError: solver diverged")

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"):
        callback.on_multirun_end(_hydra_cfg(sweep / "0", 0, sweep))
    n = len(collect.collect_runs(sweep))
    assert f"sweep finished: {n - 3} of {n} jobs ok" in caplog.text
    assert "ValueError: n_dips too large" in caplog.text and "scripts/compare.py" in caplog.text


def _load_compare():
    return load_script("compare")


def test_compare_writes_tables_and_figures(sweep, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert _load_compare().main([str(sweep), "-o", str(out), "--x", "dips_percent"]) == 0
    printed = capsys.readouterr().out
    n = len(collect.collect_runs(sweep))
    assert f"{n - 3} of {n} jobs finished" in printed and "ValueError: n_dips too large" in printed
    for name in ("vs_dips.png", "vs_snr.png", "montage.png"):
        assert _is_png(out / name), name
    with (out / "runs.csv").open() as f:
        assert len(list(csv.DictReader(f))) == n
    with (out / "summary.csv").open() as f:
        summary = list(csv.DictReader(f))
    assert len(summary) == len(SOLVERS) * len(DIPS) + len(SNRS)
    md = (out / "summary.md").read_text()
    assert md.startswith("| solver | dips | SNR (dB) | runs |") and "Failed or unfinished jobs (3 of" in md


def _compare_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "compare.py"), *args],
                          capture_output=True, text=True, timeout=120)


def test_compare_cli_errors_on_empty_and_unfinished_dirs(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = _compare_cli(str(empty))
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"error: {empty}: no reconstruction jobs found (no "
                                                ".hydra/config.yaml, metrics.json or error.txt below it); "
                                                "pass the directory of a sweep (`-m`) or of a run"]

    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "multirun.yaml").write_text("hydra: {}\n")
    write_job(partial / "0", solver="lsmr", n_dips=4, snr_db=None, seed=0, metrics=None)
    (partial / "1").mkdir()
    proc = _compare_cli(str(partial))
    assert proc.returncode == 1
    assert "0 of 2 jobs finished" in proc.stdout and "no job in" in proc.stderr
    assert proc.stderr.count("\n") == 1                               # one line
