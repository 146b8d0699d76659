"""scripts/paper_figures.py: the Fig. 11 / Fig. 13a jobs through the pipeline, on a tiny grid."""

from __future__ import annotations

import json
import re

import pytest
from script_modules import load_script



@pytest.fixture(scope="module")
def paper_figures():
    return load_script("paper_figures")


def test_job_overrides_take_the_percent_of_n_squared(paper_figures):
    overrides = paper_figures.job_overrides("bunny", 64, 1.0, ["solver=voxel"])
    assert "n_dips=41" in overrides and "resolution=64" in overrides  # ceil(0.01 * 4096)
    assert "n_dips=1639" in paper_figures.job_overrides("hand", 128, 10.0, [])  # ceil(1638.4)
    assert overrides[-1] == "solver=voxel"  # the command line wins


def test_overrides_add_to_the_default_solver_and_say_which_defaults_they_replace(paper_figures):
    """Before: any override replaced the default ``solver=minnorm solver.iter_lim=60`` without a word (``threads=1``
    ran minnorm with its config's 300 LSMR iterations)."""
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        threads = compose(config_name="config", overrides=paper_figures.job_overrides("bunny", 16, 5.0, ["threads=1"]))
        longer = compose(config_name="config",
                         overrides=paper_figures.job_overrides("bunny", 16, 5.0, ["solver.iter_lim=300"]))
    assert (threads.solver.iter_lim, threads.threads, threads.operator.backend) == (60, 1, "fourier")
    assert longer.solver.iter_lim == 300 and longer.solver._target_.endswith("MinNormSolver")
    assert paper_figures.replaced_note(["threads=1"]) is None
    assert paper_figures.replaced_note(["solver=minnorm"]) is None  # the default's own choice replaces nothing
    assert paper_figures.replaced_note(["solver=voxel", "threads=1"]) == (
        "note: solver=voxel replaces the defaults solver=minnorm solver.iter_lim=60; operator=fourier "
        "operator.eps=1e-3 operator.upsampfac=1.25 operator.single=true still apply")
    assert paper_figures.replaced_note(["solver.iter_lim=300"]).startswith(
        "note: solver.iter_lim=300 replaces the default solver.iter_lim=60; ")


def test_another_operator_drops_the_default_operators_options(paper_figures, tmp_path, capsys):
    """Before: ``operator=splat`` ended in Hydra's "Could not override 'operator.eps'. To append to your config use
    +operator.eps=1e-3", exit 2: the default fourier operator's options stayed."""
    out = tmp_path / "figs"
    assert paper_figures.main(["operator=splat", "--n", "12", "--percent", "10", "--meshes", "bunny",
                               "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("note: operator=splat replaces the defaults operator=fourier operator.eps=1e-3 "
                              "operator.upsampfac=1.25 operator.single=true; solver=minnorm solver.iter_lim=60 "
                              "still apply\n"), printed
    recorded = json.loads((out / "bunny_n12_p10" / "overrides.json").read_text())
    assert recorded[-3:] == ["solver=minnorm", "solver.iter_lim=60", "operator=splat"]
    assert json.loads((out / "bunny_n12_p10" / "metrics.json").read_text())["operator"] == "splat"


@pytest.mark.parametrize("percent", ["nan", "inf", "-5"])
def test_a_share_that_is_no_percentage_is_refused_naming_it(paper_figures, capsys, percent):
    """``paper_figures.py --percent nan``: before, a ``ValueError: cannot convert float NaN to integer`` traceback,
    exit 1 (``inf`` alike); now one argparse error naming the value, exit 2, before any job."""
    with pytest.raises(SystemExit) as exit_:
        paper_figures.parse_args(["--n", "16", "--percent", percent, "--out", "unused"])
    err = capsys.readouterr().err
    expected = ("--percent must be finite, positive shares of N^2 and --n at least 8, got --percent "
                f"{float(percent):g} and --n 16")
    assert exit_.value.code == 2 and expected in err, err


@pytest.mark.parametrize("argv,message", [
    (["--n", "16", "--percent", "0.1"], r"--percent 0.1 at --n 16 asks 0.256 dips: the job would run 1 \(0.391 % of "
                                        r"N\^2\), tabled as 0.1 %; give a larger --n or --percent \(7.81 % or more"),
    (["--n", "8"], r"--percent 1 at --n 8 asks 0.64 dips: the job would run 1 \(1.56 % of N\^2\), tabled as 1 %"),
])
def test_a_share_that_rounds_to_another_budget_is_refused(paper_figures, capsys, argv, message):
    """``paper_figures.py --n 16 --percent 0.1`` (and ``--n 8`` with the default 1/3/10 %): before, exit 0 with
    1 dip (0.39 % of 16^2; 1.56 % and 3.1 % of 8^2) tabled, drawn and printed (``RESULT chamfer_0.1=0.1655``) as the
    asked share. A count rounded up by more than 5 % is refused before any job; the paper's sizes and the other
    tests' (13 dips for 5 % of 16^2, 15 for 10 % of 12^2) run."""
    with pytest.raises(SystemExit) as exit_:
        paper_figures.parse_args([*argv, "--out", "unused"])
    assert exit_.value.code == 2 and re.search(message, capsys.readouterr().err)
    for ok in (["--n", "64", "128"], ["--n", "16", "--percent", "5", "20"], ["--n", "12", "--percent", "10"]):
        paper_figures.parse_args(ok)


def test_figures_and_table_from_a_tiny_sweep(paper_figures, tmp_path, capsys):
    out = tmp_path / "figs"
    # 5 and 20 % of 16^2 (13 and 52 dips a mesh; 10 and 40 % before, twice the simulated dips): measured
    # Chamfer 0.031 and 0.013 (10 and 40 %: 0.018 and 0.012), so the budgets stay well apart
    args = ["--n", "16", "--meshes", "bunny", "spot", "--percent", "5", "20", "--out", str(out)]
    assert paper_figures.main(args) == 0
    printed = capsys.readouterr().out
    for name in ("fig13a.png", "fig11_n16.png", "summary.md", "runs.csv"):
        assert (out / name).stat().st_size > 0, name
    result = dict(item.split("=") for item in printed.strip().splitlines()[-1].split()[1:])
    assert set(result) == {"chamfer_5", "hausdorff_5", "chamfer_20", "hausdorff_20"}
    # more dips, smaller mean surface error (averaged over the two meshes)
    assert 0 < float(result["chamfer_20"]) < float(result["chamfer_5"]) < 0.2
    # finished jobs are reused: a second call runs nothing and prints the same numbers
    mtime = (out / "bunny_n16_p5" / "metrics.json").stat().st_mtime
    assert paper_figures.main(args) == 0
    assert (out / "bunny_n16_p5" / "metrics.json").stat().st_mtime == mtime
    assert capsys.readouterr().out.strip().splitlines()[-1] == printed.strip().splitlines()[-1]
    # another solver into the same --out: the finished minnorm jobs are not tabled as its numbers
    assert paper_figures.main(["solver=voxel", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out} holds finished jobs of another setting (bunny_n16_p5 was made with ")
    assert "solver=minnorm" in err and "(now solver=voxel)" in err and "use another --out" in err
    assert (out / "bunny_n16_p5" / "metrics.json").stat().st_mtime == mtime


def test_summary_shows_undefined_metrics_as_dashes(paper_figures):
    # an empty truth has no IoU and an empty result no Chamfer: metrics.json holds null, not a number
    rows = [{"shape": "plate", "resolution": 16, "n_dips": 26, "percent": 10.0, "status": "ok", "iou": None,
             "chamfer": None, "hausdorff": None, "seconds": 1.5},
            {"shape": "bunny", "resolution": 16, "n_dips": 26, "percent": 10.0, "status": "ok", "iou": 0.9,
             "chamfer": 0.012, "hausdorff": 0.05, "seconds": 2.0}]
    groups = paper_figures.collect.aggregate(rows, ("percent",), metrics=("iou", "chamfer", "hausdorff"))
    table = paper_figures.summary(rows, groups)
    assert "| plate | 16 | 26 | 10 | - | - | - | 1.5 |" in table
    assert "| bunny | 16 | 26 | 10 | 0.900 | 0.0120 | 0.0500 | 2.0 |" in table
    assert "| 10 | 2 | 0.0120 +- 0.0000 | 0.0500 +- 0.0000 |" in table  # the mean over the defined ones
    only_undefined = paper_figures.collect.aggregate(rows[:1], ("percent",), metrics=("chamfer", "hausdorff"))
    assert "| 10 | 1 | - +- - | - +- - |" in paper_figures.summary(rows[:1], only_undefined)


def test_the_table_and_result_hold_only_the_jobs_asked_for(paper_figures, tmp_path, capsys):
    """A second call into the same ``--out`` with another mesh: its table and RESULT line are that mesh's
    alone, not pooled with the first call's finished jobs (which stay on disk, untouched)."""
    out = tmp_path / "figs"
    base = ["--n", "12", "--percent", "10", "--out", str(out)]
    assert paper_figures.main([*base, "--meshes", "bunny"]) == 0
    capsys.readouterr()
    assert paper_figures.main([*base, "--meshes", "hand"]) == 0
    printed = capsys.readouterr().out
    assert "| hand | 12 |" in printed and "| bunny |" not in printed and "| 10 | 1 |" in printed
    hand = json.loads((out / "hand_n12_p10" / "metrics.json").read_text())
    result = dict(item.split("=") for item in printed.strip().splitlines()[-1].split()[1:])
    assert result["chamfer_10"] == f"{hand['chamfer']:.4f}"
    assert (out / "bunny_n12_p10" / "metrics.json").is_file()


@pytest.mark.parametrize("argv, message", [
    (["resolution=16"], "override resolution=16: paper_figures.py sets resolution for each job .* give --n instead"),
    (["+n_dips=5"], "override \\+n_dips=5: .* give --percent instead"),
    (["shape.path=x.ply"], "override shape.path=x.ply: .* give --meshes instead"),
    (["solver=foo"], "In 'config': Could not find 'solver/foo'"),
    (["--meshes", "bunnyy"], "no bundled mesh 'bunnyy'; bundled: boot, "),
])
def test_settings_the_jobs_cannot_run_with_are_one_line_and_exit_2(paper_figures, tmp_path, capsys, argv, message):
    """An override of what each job sets from --n, --percent or --meshes (``resolution=16`` ran every job at 16^3
    with the dips of 12^3, tabled as N 16 at '10 %' though 15 dips are 5.9 % of 16^2), an unknown config choice
    (a traceback) or a mesh name that is not bundled (a failed job): one ``error:`` line, exit 2, no job."""
    out = tmp_path / "figs"
    argv = [*argv, "--n", "12", "--percent", "10", "--out", str(out)]
    argv += [] if "--meshes" in argv else ["--meshes", "bunny"]
    with pytest.raises(SystemExit) as exit_:
        paper_figures.main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and re.match(f"error: {message}", err), err
    assert not out.exists()


@pytest.mark.parametrize("under_a_file", [False, True])
def test_an_out_that_cannot_hold_the_jobs_is_one_line_and_exit_2(paper_figures, tmp_path, capsys, under_a_file):
    """``--out notes.txt`` (a file) or ``--out notes.txt/figs`` printed a raw ``FileExistsError`` or
    ``NotADirectoryError`` traceback, exit 1."""
    notes = tmp_path / "notes.txt"
    notes.write_text("kept")
    out = notes / "figs" if under_a_file else notes
    with pytest.raises(SystemExit) as exit_:
        paper_figures.main(["--n", "12", "--percent", "10", "--meshes", "bunny", "--out", str(out)])
    err = capsys.readouterr().err
    message = f"{out}: Not a directory" if under_a_file else f"--out {out} is a file: give a folder"
    assert exit_.value.code == 2 and err.count("\n") == 1 and err.startswith(f"error: {message}"), err
    assert notes.read_text() == "kept"


def test_an_empty_reconstruction_is_shown_as_such_and_kept_out_of_the_means(paper_figures):
    """Before: an empty result's Chamfer and Hausdorff of 1.0 (a stand-in, one truth diagonal) were tabled as its
    distances and entered the budget's mean (0.5060 from 0.012 and the empty run's 1.0)."""
    rows = [{"shape": "hand", "resolution": 16, "n_dips": 26, "percent": 10.0, "status": "ok", "iou": 0.0,
             "chamfer": 1.0, "hausdorff": 1.0, "empty": True, "seconds": 1.5},
            {"shape": "bunny", "resolution": 16, "n_dips": 26, "percent": 10.0, "status": "ok", "iou": 0.9,
             "chamfer": 0.012, "hausdorff": 0.05, "empty": False, "seconds": 2.0}]
    groups = paper_figures.collect.aggregate(rows, ("percent",), metrics=("iou", "chamfer", "hausdorff"))
    table = paper_figures.summary(rows, groups)
    assert "| hand | 16 | 26 | 10 | 0.000 | empty | empty | 1.5 |" in table
    assert "| 10 | 2 (1 empty, not in the means) | 0.0120 +- 0.0000 | 0.0500 +- 0.0000 |" in table
