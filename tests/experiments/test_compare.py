"""scripts/compare.py on a synthetic sweep directory whose metrics follow known formulas: tables and figures
written, one-line errors on empty and unfinished directories."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from dipnet.experiments import collect, figures

from script_modules import load_script
from sweep_fixtures import DIPS, SNRS, SOLVERS, is_png, write_job, write_sweep

ROOT = Path(__file__).resolve().parents[2]
@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return write_sweep(tmp_path_factory.mktemp("sweep"))


def _load_compare():
    return load_script("compare")


def test_compare_writes_tables_and_figures(sweep, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert _load_compare().main([str(sweep), "-o", str(out), "--x", "dips_percent"]) == 0
    printed = capsys.readouterr().out
    n = len(collect.collect_runs(sweep))
    assert f"{n - 3} of {n} jobs finished" in printed and "ValueError: n_dips too large" in printed
    for name in ("vs_dips.png", "vs_snr.png", "montage.png"):
        assert is_png(out / name), name
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


def test_compare_cli_errors_on_an_empty_dir(tmp_path):
    """The real entry point (``sys.exit(main())``): exit status 2 and one ``error:`` line."""
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = _compare_cli(str(empty))
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"error: {empty}: no reconstruction jobs found (no "
                                                ".hydra/config.yaml, metrics.json or error.txt below it); "
                                                "pass the directory of a sweep (`-m`) or of a run"]


def quiet_main(argv: list[str], capsys, caplog, recwarn) -> tuple[int, str, str]:
    """``compare.main(argv)`` in-process (the CLI's exit code and streams without a subprocess's ~6 s of
    importing torch): ``(return code, stdout, stderr)``, after checking that it logged no warning and
    raised no Python warning (but a deprecation one), which a subprocess would have printed to its stderr too."""
    with caplog.at_level("WARNING"):
        code = _load_compare().main(argv)
    out, err = capsys.readouterr()
    shown = [w for w in recwarn.list if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning))]
    assert not caplog.records and not shown, ([r.getMessage() for r in caplog.records], [str(w.message) for w in shown])
    return code, out, err


def test_compare_errors_on_an_unfinished_dir(tmp_path, capsys, caplog, recwarn):
    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "multirun.yaml").write_text("hydra: {}\n")
    write_job(partial / "0", solver="lsmr", n_dips=4, snr_db=None, seed=0, metrics=None)
    (partial / "1").mkdir()
    code, out, err = quiet_main([str(partial)], capsys, caplog, recwarn)
    assert code == 1
    assert "0 of 2 jobs finished" in out and "no job in" in err
    assert err.count("\n") == 1                                      # one line


REFUSED_LOG = ("[2026-11-28 02:18:40,979][dipnet][ERROR] - error: option n_dips is ignored with planner=adaptive "
               "(the planner chooses the dips: set planner.budget): remove it\n")


def test_compare_on_a_refused_run_reports_its_error(tmp_path, capsys, caplog, recwarn):
    """Before: "(unfinished): no metrics.json (unfinished or killed)" for a run that ``reconstruct.py``
    refused, although its log holds the ``error:`` line."""
    run = write_job(tmp_path / "run", solver="lsmr", n_dips=8, snr_db=None, seed=0, metrics=None)
    (run / "reconstruct.log").write_text(REFUSED_LOG)
    code, out, err = quiet_main([str(run)], capsys, caplog, recwarn)
    message = ("option n_dips is ignored with planner=adaptive (the planner chooses the dips: set planner.budget): "
               "remove it (reconstruct.log)")
    assert code == 1 and f"(failed): {message}" in out and "(unfinished)" not in out
    assert err == f"error: the run in {run} failed: {message}\n"


def test_a_sweep_of_recordings_is_compared_without_a_truth(tmp_path, capsys):
    sweep = tmp_path / "sw"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra: {}\n")
    for i, solver in enumerate(("minnorm", "lsqr")):
        write_job(sweep / str(i), solver=solver, n_dips=8, snr_db=None, seed=0, ndim=3, shape="chamber_box",
                  recording="/data/torus.npz", metrics={"profile_residual": 0.1 + i, "volume_ratio": 1.1})
    out = tmp_path / "cmp"
    assert _load_compare().main([str(sweep), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "these runs have no ground truth (recorded sources), so no IoU or Chamfer" in printed
    summary = (out / "summary.md").read_text()
    assert summary.startswith("| solver | dips | SNR (dB) | runs | profile residual | volume ratio | seconds |")
    assert "These runs have no ground truth (recorded sources)" in summary  # the table's file says it too
    assert is_png(out / "vs_dips.png") and is_png(out / "montage.png")
    with (out / "runs.csv").open() as f:
        assert {row["shape"] for row in csv.DictReader(f)} == {"torus"}


def test_a_sweep_with_nothing_to_compare_is_one_error_line(tmp_path, capsys, caplog, recwarn):
    sweep = tmp_path / "sw"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra: {}\n")
    job = write_job(sweep / "0", solver="lsqr", n_dips=8, snr_db=None, seed=0, recording="/data/torus.npz",
                    metrics={})
    (job / "metrics.json").write_text('{"solver": "lsqr"}')
    code, _, err = quiet_main([str(sweep)], capsys, caplog, recwarn)  # a traceback would fail the test here
    assert code == 1
    assert err.startswith("error: the finished jobs record none of profile_residual, volume_ratio, seconds")
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("differ", ["resolution", "seed"])
def test_a_row_pooling_runs_of_another_resolution_is_named(tmp_path, capsys, differ):
    """Two runs of one solver x dips x SNR row at 12^3 and 24^3: a warning and a note under the table name
    the resolution and the --by that splits them; two seeds of one setting are replicates: no note."""
    sweep = tmp_path / "sw"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra: {}\n")
    for i in range(2):
        write_job(sweep / str(i), solver="minnorm", n_dips=20, snr_db=None, ndim=3, metrics={"iou": 0.8 + 0.1 * i},
                  **({"resolution": 12 * (i + 1), "seed": 0} if differ == "resolution" else {"seed": i}))
    out = tmp_path / "cmp"
    assert _load_compare().main([str(sweep), "-o", str(out)]) == 0
    err, md = capsys.readouterr().err, (out / "summary.md").read_text()
    note = ("ows of this table pool runs that differ in resolution (12, 24): their mean ± std mixes those settings; "
            "split them with `--by solver n_dips snr_db resolution`")
    if differ == "resolution":
        assert f"warning: r{note}" in err and f"\nR{note}" in md
    else:
        assert "pool runs" not in err + md


def test_a_job_given_twice_is_compared_once(sweep, tmp_path, capsys):
    """``compare.py SWEEP SWEEP/0`` (a sweep and one of its jobs, as a shell glob gives): before, job 0 was read
    twice, its row showed "runs 3" for two seeds (its mean weighted to job 0), exit 0 without a word."""
    out = tmp_path / "cmp"
    n = len(collect.collect_runs(sweep))
    assert _load_compare().main([str(sweep), str(sweep / "0"), str(sweep), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {n + 1} job(s) were given more than once (the same directory twice, or a sweep and its own " \
           f"jobs): {sweep / '0'}, " in err and "each is compared once" in err
    with (out / "runs.csv").open() as f:
        assert len(list(csv.DictReader(f))) == n
    with (out / "summary.csv").open() as f:
        assert {row["runs"] for row in csv.DictReader(f)} <= {"1", "2"}


def test_files_of_an_earlier_comparison_in_the_output_folder_are_named(sweep, tmp_path, capsys):
    """``compare.py A -o results`` then ``compare.py B -o results`` (the README gives ``-o results``): before, the
    folder kept A's ``vs_snr.png`` (B has no noise levels) beside B's tables, exit 0 without a word."""
    out = tmp_path / "results"
    assert _load_compare().main([str(sweep), "-o", str(out)]) == 0
    assert (out / "vs_snr.png").is_file() and "earlier comparison" not in capsys.readouterr().err
    quiet = tmp_path / "quiet"
    for i, n in enumerate((4, 8)):
        write_job(quiet / str(i), solver="minnorm", n_dips=n, snr_db=None, seed=0, metrics={"iou": 0.5})
    assert _load_compare().main([str(quiet), "-o", str(out)]) == 0
    assert capsys.readouterr().err.endswith(
        f"warning: {out} holds 1 file(s) of an earlier comparison that this one did not write: vs_snr.png; they are "
        "not this comparison's results: delete them, or give each comparison its own -o\n")
    assert _load_compare().main([str(quiet), "-o", str(out)]) == 0  # the same comparison again: vs_snr.png still
    assert "vs_snr.png" in capsys.readouterr().err


def test_the_noise_curves_keep_runs_of_other_dip_counts_apart(tmp_path, monkeypatch):
    """A sweep ``snr_db=10,30 n_dips=6,40`` (16^3, minnorm, measured: false positives 0.508 / 0.473 at 6 dips,
    0.157 / 0.190 at 40): before, ``vs_snr.png`` drew one point per solver x SNR, the mean of the 6-dip and the
    40-dip run (0.333 at 10 dB, its error bar their spread), while the table kept them apart; now one line per
    dip count."""
    sweep = tmp_path / "sw"
    fp = {(6, 10.0): 0.508, (6, 30.0): 0.473, (40, 10.0): 0.157, (40, 30.0): 0.190}
    for i, ((n, snr), value) in enumerate(fp.items()):
        write_job(sweep / str(i), solver="minnorm", n_dips=n, snr_db=snr, seed=0,
                  metrics={"iou": 0.8, "false_positive": value, "false_negative": 0.0})
    drawn = {}

    def plot(groups, path, **kwargs):
        drawn[Path(path).name] = (groups, kwargs.get("line", "solver"))
        return Path(path)

    monkeypatch.setattr(figures, "plot_vs_snr", plot)
    monkeypatch.setattr(figures, "plot_vs_dips", plot)
    assert _load_compare().main([str(sweep), "-o", str(tmp_path / "cmp")]) == 0
    for name, x in (("vs_snr.png", "snr_db"), ("vs_dips.png", "n_dips")):
        groups, line = drawn[name]
        points = {(g[line], g[x]): g["false_positive_mean"] for g in groups}
        assert len(points) == 4 and all(g["runs"] == 1 for g in groups), (name, points)
    assert {k: round(v, 3) for k, v in points.items()} == {
        ("minnorm @ 10 dB", 6): 0.508, ("minnorm @ 30 dB", 6): 0.473, ("minnorm @ 10 dB", 40): 0.157,
        ("minnorm @ 30 dB", 40): 0.19}
    assert {g[drawn["vs_snr.png"][1]] for g in drawn["vs_snr.png"][0]} == {"minnorm, 6 dips", "minnorm, 40 dips"}


@pytest.mark.parametrize("flag", ["--by", "--rows"])
def test_a_column_no_run_records_is_refused(sweep, tmp_path, capsys, flag):
    """``compare.py SWEEP --by solvr`` (a typo): before, exit 0 with one row pooling every run of the sweep (the
    minnorm and voxel runs of two shapes, 4 jobs, as one mean) and a warning listing every option; ``--rows shap``
    drew a montage of one row, one run per column. Now one ``error:`` line naming the column, exit 2, nothing
    written."""
    out = tmp_path / "cmp"
    assert _load_compare().main([str(sweep), "-o", str(out), flag, "solver", "solvr"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {flag} solvr: no run records 'solvr', so every run would fall in one group; "
                          "choose among the axes (solver, shape, ndim, resolution, n_dips, dips_percent, snr_db, "
                          "seed), "
                          "the options the runs set (n_dips, seed, solver)") and err.count("\n") == 1, err
    assert not out.exists()


def test_an_output_path_that_is_a_file_is_refused_in_one_line(sweep, tmp_path, capsys):
    """``compare.py SWEEP -o notes.txt`` (an existing file) printed a raw ``FileExistsError`` traceback."""
    out = tmp_path / "notes.txt"
    out.write_text("kept")
    assert _load_compare().main([str(sweep), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == f"error: --out {out} is a file: give a folder for the comparison's tables and plots\n"
    assert out.read_text() == "kept"


def test_an_output_folder_that_cannot_be_created_is_refused_in_one_line(sweep, tmp_path, capsys):
    """``compare.py SWEEP -o notes.txt/results`` (a folder under a file; alike a missing or read-only mount)
    printed a raw ``NotADirectoryError`` traceback."""
    (tmp_path / "notes.txt").write_text("kept")
    out = tmp_path / "notes.txt" / "results"
    assert _load_compare().main([str(sweep), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out {out}: cannot create the folder") and err.count("\n") == 1, err
    assert (tmp_path / "notes.txt").read_text() == "kept"


def test_an_output_folder_that_is_a_jobs_own_is_refused_in_one_line(tmp_path, capsys):
    """``compare.py JOB -o JOB --html`` replaced the job's own ``report.html`` with the comparison's page, and wrote
    the comparison's tables among the job's files, exit 0 without a word."""
    job = write_job(tmp_path / "job", solver="minnorm", n_dips=8, snr_db=None, seed=0, metrics={"iou": 0.9})
    (job / "report.html").write_text("the job's own page")
    assert _load_compare().main([str(job), "-o", str(job), "--html"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out {job} is the folder of the job {job}") and err.count("\n") == 1, err
    assert (job / "report.html").read_text() == "the job's own page" and not (job / "runs.csv").exists()
