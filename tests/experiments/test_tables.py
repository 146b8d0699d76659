"""A sweep's tables (dipnet.experiments.tables): the per-run CSV, the aggregated Markdown table and the list of
failed or unfinished jobs."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from dipnet.experiments import collect, tables

from sweep_fixtures import write_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return write_sweep(tmp_path_factory.mktemp("sweep"))


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


def test_the_pooled_note_names_the_settings_as_set():
    """The summary table's cells round to 3 digits; the settings a row pools are named to 6, so 0.99999 is not
    shown as 1 (not even a legal threshold)."""
    from dipnet.experiments.tables import pooled_note

    note = pooled_note({"solver.threshold": [0.5, 0.99999], "resolution": [12, 24]}, ("solver",), {"resolution"})
    assert "solver.threshold (0.5, 0.99999)" in note and "resolution (12, 24)" in note


def test_the_table_counts_the_runs_that_explain_their_data():
    """A sweep of inconsistent runs was tabled by its IoU and Chamfer alone; now a column says how many of a row's
    runs passed their consistency check (absent when no run records one)."""
    rows = [{"status": "ok", "solver": "voxel", "n_dips": 20, "snr_db": None, "iou": 0.9, "consistency": verdict}
            for verdict in ("consistent", "inconsistent", "inconsistent")]
    table = tables.markdown_table(collect.aggregate(rows), metrics=("iou",))
    assert "| runs | consistent |" in table and "| 3 | 1 of 3 |" in table
    plain = [{k: v for k, v in row.items() if k != "consistency"} for row in rows]
    assert "consistent" not in tables.markdown_table(collect.aggregate(plain), metrics=("iou",))


def test_a_rows_failed_jobs_are_counted_beside_its_means():
    """A row's mean is over its finished runs: a setting whose hard cases fail looked as good as its easy ones
    (IoU 0.95 from 2 of 3 jobs, the third failed, with only a smaller runs count to show it). Now a failed column
    counts them (absent when no job failed; a row whose every job failed stays out, in the failures list)."""
    rows = [{"status": "ok", "solver": "voxel", "n_dips": 20, "snr_db": None, "iou": iou} for iou in (0.94, 0.96)]
    rows += [{"status": "failed", "solver": "voxel", "n_dips": 20, "snr_db": None},
             {"status": "unfinished", "solver": "minnorm", "n_dips": 20, "snr_db": None}]
    (g,) = collect.aggregate(rows, metrics=("iou",))
    assert g["solver"] == "voxel" and g["runs"] == 2 and g["failed"] == 1 and g["iou_mean"] == pytest.approx(0.95)
    table = tables.markdown_table([g], metrics=("iou",))
    assert "| runs | failed | IoU |" in table and "| 2 | 1 | 0.95 ± 0.0141 |" in table
    assert "failed" not in tables.markdown_table(collect.aggregate(rows[:2]), metrics=("iou",))


def test_an_empty_reconstruction_is_counted_not_averaged_as_a_chamfer_of_1():
    """Before: an empty run's Chamfer of 1.0 (a stand-in, one truth diagonal) entered its row's mean: 0.34 ± 0.57
    from 0.01, 0.02 and the empty run's 1.0."""
    rows = [{"status": "ok", "solver": "voxel", "n_dips": 20, "snr_db": None, "iou": iou, "chamfer": chamfer,
             "hausdorff": chamfer, "empty": chamfer == 1.0} for iou, chamfer in ((0.9, 0.01), (0.8, 0.02), (0.0, 1.0))]
    (g,) = collect.aggregate(rows, metrics=("iou", "chamfer", "hausdorff"))
    assert g["runs"] == 3 and g["empty"] == 1
    assert g["chamfer_mean"] == pytest.approx(0.015) and g["hausdorff_mean"] == pytest.approx(0.015)
    assert g["iou_mean"] == pytest.approx(0.5667, abs=1e-4)  # IoU 0 is a score: it stays in
    table = tables.markdown_table([g], metrics=("iou", "chamfer"))
    assert "| runs | empty | IoU | Chamfer |" in table and "| 3 | 1 of 3 | 0.567 ± 0.493 | 0.015 ± 0.00707 |" in table
    assert collect.empty_note(rows).startswith("1 of 3 finished runs reconstructed nothing (the empty column)")
    (only,) = collect.aggregate([{**rows[2], "solver": "dip"}], metrics=("iou", "chamfer"))
    assert "chamfer_mean" not in only
    assert "| dip | 20 | none | 1 | 1 of 1 | 0 ± 0 | none (empty) |" in tables.markdown_table(
        [g, only], metrics=("iou", "chamfer"))
    assert "empty" not in tables.markdown_table(collect.aggregate(rows[:2]), metrics=("iou",))
    assert collect.empty_note(rows[:2]) == ""
