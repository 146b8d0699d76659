"""Collecting and aggregating a sweep (dipnet.experiments.collect), on a synthetic sweep directory whose metrics
follow known formulas (tests/sweep_fixtures.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from dipnet.experiments import collect

from sweep_fixtures import DIPS, SEEDS, SNRS, SOLVERS, chamfer_of, iou_of, write_job, write_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return write_sweep(tmp_path_factory.mktemp("sweep"))


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


@pytest.mark.parametrize("text", ["[1, 2]", "3", '"done"'])
def test_a_metrics_file_that_is_no_json_object_is_a_failed_row(tmp_path, text):
    """``metrics.json`` holding ``[1, 2]`` was named failed, but kept as the run's metrics: ``compare.py`` then
    died in ``run_row`` with ``AttributeError: 'list' object has no attribute 'get'``."""
    job = write_job(tmp_path / "0", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.5})
    (job / "metrics.json").write_text(text)
    run = collect.load_run(job)
    assert run.status == "failed" and "not a JSON object" in run.error and run.metrics == {}
    row = collect.run_row(run)
    assert row["status"] == "failed" and row["n_dips"] == 4


def test_a_sweep_job_that_failed_after_writing_its_metrics_is_failed(tmp_path):
    """Before: a job that raised after ``metrics.json`` (a full disk while writing its meshes) was ``ok`` in
    ``compare.py``, its error.txt unread. An error.txt older than the metrics (a failed run, then the same sweep run
    again into the folder, which succeeded) is the earlier run's: ``ok``."""
    import os

    job = write_job(tmp_path / "job", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.5})
    metrics, error = job / "metrics.json", job / "error.txt"
    error.write_text("OSError: [Errno 28] No space left on device\n\nTraceback ...")
    written = metrics.stat().st_mtime_ns
    os.utime(error, ns=(written + 10**9, written + 10**9))
    run = collect.load_run(job)
    assert (run.status, run.metrics) == ("failed", {})
    assert run.error == ("OSError: [Errno 28] No space left on device (written after its metrics.json: the job failed "
                         "once its numbers were written, so they are not tabled)")
    os.utime(error, ns=(written - 10**9, written - 10**9))
    assert collect.load_run(job).status == "ok"


def test_a_run_refused_outside_a_sweep_is_failed_with_its_logged_error(tmp_path):
    """Before: "unfinished" (no metrics.json, no error.txt) though its log ends with the ``error:`` line."""
    job = write_job(tmp_path / "job", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics=None)
    assert collect.load_run(job).status == "unfinished"  # no log yet: still starting, or killed
    log = job / "reconstruct.log"
    log.write_text("[2026-11-28 02:18:40,100][dipnet.jobs.pipeline][INFO] - building the grid\n"
                   "[2026-11-28 02:18:40,979][dipnet][ERROR] - error: resolution=3 is too coarse\n")
    run = collect.load_run(job)
    assert (run.status, run.error) == ("failed", "resolution=3 is too coarse (reconstruct.log)")
    with log.open("a") as f:  # run again into the folder (Hydra appends to the log): going on, not failed
        f.write("[2026-11-28 02:20:00,000][dipnet.jobs.pipeline][INFO] - building the grid\n")
    assert collect.load_run(job).status == "unfinished"
    log.write_text("[2026-11-28 02:18:40,979][dipnet][WARNING] - error: quoted in a warning\n")
    assert collect.load_run(job).status == "unfinished"


def test_metrics_an_earlier_run_left_in_its_folder_are_not_the_later_runs(tmp_path):
    """Before: ``reconstruct.py`` refused (or killed) in the ``hydra.run.dir`` of a finished run left that run's
    ``metrics.json`` beside its own ``.hydra/``: "ok", the earlier numbers under the new config (compare.py tabled
    a minnorm run's IoU 0.717 as ``solver=voxel``'s, exit 0)."""
    job = write_job(tmp_path / "job", solver="minnorm", n_dips=4, snr_db=None, seed=0,
                    metrics={"iou": 0.717, "overrides": ["seed=0", "solver=minnorm", "n_dips=4"]})
    assert collect.load_run(job).status == "ok"  # the same overrides, in another order
    OmegaConf.save(OmegaConf.create(["solver=voxel", "n_dips=4", "seed=0"]), job / ".hydra" / "overrides.yaml")
    run = collect.load_run(job)
    assert (run.status, run.metrics) == ("unfinished", {})
    assert run.error == ("its metrics.json is an earlier run's in this folder "
                         "(overrides: seed=0 solver=minnorm n_dips=4), "
                         "not this run's (solver=voxel n_dips=4 seed=0): this run wrote none "
                         "(still running, or killed)")
    (job / "reconstruct.log").write_text("[2026-11-28 06:52:52,521][dipnet][ERROR] - error: snr_db must be ...\n")
    run = collect.load_run(job)
    assert run.status == "failed" and run.error.startswith("snr_db must be ... (reconstruct.log); its metrics.json is")
    assert "iou" not in collect.run_row(run)


def test_a_run_with_a_declared_symmetry_is_tabled_by_the_dips_it_measured(tmp_path):
    """Before: ``n_dips=10 symmetry={n_fold: 4}`` was a 40-dip row (its metrics' ``n_dips`` counts the images it
    solves), pooled with the 40-dip runs without symmetry, its % of dips four times its cost."""
    plain = write_job(tmp_path / "plain", solver="minnorm", n_dips=40, snr_db=None, seed=0, metrics={"iou": 0.9})
    sym = write_job(tmp_path / "sym", solver="minnorm", n_dips=10, snr_db=None, seed=0,
                    metrics={"iou": 0.8, "n_dips": 40, "n_dips_measured": 10})
    rows = collect.run_rows(collect.collect_runs([plain, sym]))
    assert [(r["n_dips"], r.get("n_dips_with_images")) for r in rows] == [(40, None), (10, 40)]
    assert rows[1]["dips_percent"] == pytest.approx(rows[0]["dips_percent"] / 4)
    assert [g["n_dips"] for g in collect.aggregate(rows)] == [10, 40]


def test_a_recorded_run_is_not_tabled_as_noise_free(tmp_path):
    """The audit's case: a recorded run's SNR column read "none", as a noise-free simulation's does."""
    simulated = write_job(tmp_path / "sim", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.9})
    recorded = write_job(tmp_path / "rec", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.9},
                         recording="scan.jsonl")
    rows = collect.run_rows(collect.collect_runs([simulated, recorded]))
    assert [r["snr_db"] for r in rows] == [None, "recorded"]
    groups = [g["snr_db"] for g in collect.aggregate(rows)]
    assert len(groups) == 2 and set(groups) == {None, "recorded"}  # two groups, not pooled


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


def test_label_series_adds_noise_only_when_it_varies():
    rows = [{"status": "ok", "solver": "a", "snr_db": None}, {"status": "ok", "solver": "a", "snr_db": 30.0}]
    assert [r["series"] for r in collect.label_series(rows)] == ["a @ no noise", "a @ 30 dB"]
    assert [r["series"] for r in collect.label_series(rows[:1])] == ["a"]


def test_a_recorded_run_is_labelled_by_its_recording_not_the_unused_shape(tmp_path):
    torus = write_job(tmp_path / "0", solver="lsqr", n_dips=4, snr_db=None, seed=0, shape="chamber_box",
                      recording="/data/torus_scan.npz", metrics={"profile_residual": 0.1, "volume_ratio": 1.0})
    cats = write_job(tmp_path / "1", solver="lsqr", n_dips=4, snr_db=None, seed=0, shape="chamber_box",
                     recording="/data/real/3cats_fixture_3mm.csv", metrics={"profile_residual": 0.2})
    rerun = write_job(tmp_path / "2", solver="lsqr", n_dips=4, snr_db=None, seed=0, shape="chamber_box",
                      recording="/runs/base/measurement.npz", metrics={"profile_residual": 0.2})
    assert [collect.run_row(collect.load_run(j))["shape"] for j in (torus, cats, rerun)] == \
        ["torus_scan", "3cats_fixture_3mm", "base/measurement"]


def test_runs_without_a_truth_are_compared_on_what_they_record():
    truth = {"status": "ok", "iou": 0.9, "chamfer": 0.01, "profile_residual": 0.1}
    recorded = {"status": "ok", "profile_residual": 0.1, "volume_ratio": 1.0}
    assert collect.compared_metrics([truth, {"status": "failed"}]) == collect.METRICS
    assert collect.truth_note([truth]) == ""
    assert collect.compared_metrics([recorded]) == collect.DATA_METRICS == ("profile_residual", "volume_ratio",
                                                                             "seconds")
    assert collect.curve_metrics(collect.DATA_METRICS) == ("profile_residual", "volume_ratio")
    assert collect.truth_note([recorded]).startswith("these runs have no ground truth")
    mixed = collect.compared_metrics([truth, recorded])
    assert mixed[:2] == ("iou", "chamfer") and mixed[-3:] == collect.DATA_METRICS
    assert collect.truth_note([truth, recorded]).startswith("1 of 2 finished runs have no ground truth")


def test_runs_whose_iou_reference_is_approximate_are_named():
    """The chamber box at 25^3: no level makes its binary reference hold the exact volume (19.5 % off); the job's
    log warned, the comparison's tables showed its IoU like any other. Now the note says which runs and how far."""
    exact = {"status": "ok", "iou": 0.9, "truth_binary_volume_error": 0.001}
    faces = {"status": "ok", "iou": 0.8, "truth_binary_volume_error": -0.195}
    empty = {"status": "ok", "iou": float("nan"), "truth_binary_volume_error": -1.0}  # IoU undefined, warned apart
    assert collect.truth_note([exact, empty]) == ""
    note = collect.truth_note([exact, faces, {"status": "failed", "truth_binary_volume_error": 0.3}])
    assert note.startswith("1 of 2 runs with a ground truth have an approximate IoU") and "up to 19.5% off" in note


def test_null_metrics_of_strict_json_are_read_as_no_value(tmp_path):
    """metrics.json writes a non-finite number as null (dipnet.core.strict_json): rows and groups skip it."""
    for i, iou in enumerate((0.5, None, 0.7)):
        write_job(tmp_path / str(i), solver="lsmr", n_dips=4, snr_db=None, seed=i,
                  metrics={"iou": iou, "chamfer": None, "hull_fill": None})
    rows = collect.run_rows(collect.collect_runs(tmp_path))
    assert [r["status"] for r in rows] == ["ok"] * 3 and rows[1]["iou"] is None
    (g,) = collect.aggregate(rows, by=("solver",))
    assert g["runs"] == 3 and g["iou_mean"] == pytest.approx(0.6) and "chamfer_mean" not in g


def test_runs_with_an_option_set_to_an_empty_mapping_are_compared(tmp_path):
    """``'solver.surface_refit={}'`` (the refit with its defaults) leaves an empty mapping in the job's config: the
    runs that set it and those that do not are named as pooled, not a crash (a dict does not hash)."""
    runs = []
    for seed, refit in ((0, {}), (1, None)):
        job = write_job(tmp_path / str(seed), solver="voxel", n_dips=8, snr_db=None, seed=seed, metrics={"iou": 0.9})
        config = OmegaConf.load(job / ".hydra" / "config.yaml")
        config.solver.surface_refit = refit
        OmegaConf.save(config, job / ".hydra" / "config.yaml")
        runs.append(collect.load_run(job))
    assert collect.flat_config(runs[0].config)["solver.surface_refit"] == "{}"
    assert collect.pooled_options(runs, collect.run_rows(runs)) == {"solver.surface_refit": ["{}", None]}


def test_a_non_numeric_iou_is_warned_naming_the_run_and_value(tmp_path):
    """``"iou": "0.8"`` was left out of the statistics, and the IoU column dropped from the tables, without a word."""
    write_job(tmp_path / "0", solver="minnorm", n_dips=4, snr_db=None, seed=0, metrics={"iou": 0.5})
    write_job(tmp_path / "1", solver="minnorm", n_dips=4, snr_db=None, seed=1, metrics={"iou": "0.8"})
    with pytest.warns(UserWarning, match=r"1: metrics\.json's iou is '0\.8', not a number") as caught:
        runs = collect.collect_runs(tmp_path)
    assert len([w for w in caught if "not a number" in str(w.message)]) == 1  # the numeric run is not named
    assert [r.status for r in runs] == ["ok", "ok"]
