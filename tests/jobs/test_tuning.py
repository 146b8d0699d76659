"""scripts/tune.py: Optuna (ask and tell) over the ordinary pipeline, on tiny jobs."""

from __future__ import annotations

import json
import sys
from types import SimpleNamespace

import pytest
from omegaconf import OmegaConf

from hydra import compose, initialize_config_module

from dipnet.experiments import collect
from dipnet.jobs import tuning
from dipnet.jobs.scan import scan_from_config
from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.jobs.tuning import Param
from script_modules import load_script

TINY = ["resolution=16", "n_dips=12", "solver.iterations=15", "output.uncertainty=false", "output.resolvability=false"]


@pytest.fixture(scope="module")
def tune_script():
    return load_script("tune")


@pytest.fixture(autouse=True)
def no_optuna_handler():
    """Optuna's own log handler (and its colour formatter) keeps the ``sys.stderr`` of the moment it was made:
    made under another test's ``capsys`` (which test imports optuna first depends on the order, which differs
    between pytest-xdist workers), a capture closed since, each of its lines adds a "Logging error" to the
    stderr a test here reads. It is off during these tests (they read dipnet's lines, not optuna's)."""
    import optuna

    optuna.logging.disable_default_handler()
    yield
    optuna.logging.enable_default_handler()


@pytest.mark.slow
def test_a_study_runs_its_trials_and_keeps_the_best(tmp_path, monkeypatch, tune_script):
    received = []  # the weight each job's solver was configured with
    real_run = tuning.run

    def spy(cfg, out):
        received.append(cfg.solver.priors.tv.weight)
        return real_run(cfg, out)

    monkeypatch.setattr(tuning, "run", spy)
    out = tmp_path / "study"
    assert tune_script.main(["--trials", "3", "--startup-trials", "2", "--out", str(out),
                             "--param", "solver.priors.tv.weight=1e-3:1e-1", *TINY]) == 0
    best = OmegaConf.load(out / "best.yaml")
    metrics = {i: json.loads((out / str(i) / "metrics.json").read_text()) for i in range(3)}
    chamfers = {i: m["chamfer"] for i, m in metrics.items()}
    assert best.trials == 3 and best.failed == 0
    # the consistent trials first, then the lowest Chamfer
    ranked = min(metrics, key=lambda i: (metrics[i]["consistency"] == "inconsistent", chamfers[i]))
    assert best.trial == ranked and chamfers[best.trial] == best.chamfer
    assert best.consistency == metrics[ranked]["consistency"]
    assert len(set(received)) == 3 and all(1e-3 <= w <= 1e-1 for w in received)
    assert best.params["solver.priors.tv.weight"] == received[best.trial]
    # each trial directory is a sweep job that scripts/compare.py reads
    runs = collect.collect_runs([out])
    assert sorted(r.status for r in runs) == ["ok"] * 3
    assert {r.config["solver"]["priors"]["tv"]["weight"] for r in runs} == set(received)


def test_a_failing_job_is_a_failed_trial(tmp_path):
    with pytest.raises(RuntimeError, match="every trial failed"):
        tuning.tune(tmp_path, n_trials=2, overrides=[*TINY, "solver.lr=-1"])
    assert all("lr" in (tmp_path / str(i) / "error.txt").read_text() for i in range(2))


@pytest.mark.parametrize("text,param", [
    ("solver.lr=0.01:0.3", Param("solver.lr", 0.01, 0.3, True)),
    ("fill=0.5:0.95:linear", Param("fill", 0.5, 0.95, False)),
])
def test_a_tuned_option_parses(text, param):
    assert Param.parse(text) == param


@pytest.mark.parametrize("text", ["solver.lr", "solver.lr=0.3:0.01", "solver.lr=0:1", "x=1:2:cubic"])
def test_a_bad_tuned_option_is_refused(text):
    with pytest.raises(ValueError, match="LOW"):
        Param.parse(text)


@pytest.mark.parametrize("text", ["solver.lr=0.001:inf", "fill=-inf:0.9:linear"])
def test_a_tuned_range_with_an_infinite_end_is_refused(text):
    """``tune.py --param solver.lr=0.001:inf`` ran the study and died in its first trial with numpy's
    ``OverflowError: Range exceeds valid bounds`` (a traceback, exit 1)."""
    with pytest.raises(ValueError, match=r"LOW and HIGH must be finite numbers"):
        Param.parse(text)


@pytest.mark.parametrize("argv, message", [
    (["--trials", "0"], "error: the number of trials (--trials) must be a positive integer, got 0"),
    (["--trials", "2", "resolution=-3"], "error: resolution must be an integer >= 4 (voxels per axis), got -3"),
    # an override of a tuned option: every trial ran with the tuned values instead, without a word
    (["--trials", "2", "solver.priors.tv.weight=0.5"], "error: override solver.priors.tv.weight=0.5 sets "
     "solver.priors.tv.weight, which the study tunes (one of the options tuned by default, without --param): each "
     "trial's value would replace it; an option must be either fixed by an override or tuned, not both"),
])
def test_a_study_that_cannot_run_is_one_line_before_any_trial(tmp_path, capsys, tune_script, argv, message):
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--out", str(tmp_path / "study"), *argv])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == f"{message}\n"
    assert not (tmp_path / "study").exists()
    with pytest.raises(ValueError, match="must be"):
        tuning.tune(tmp_path / "study", n_trials=int(argv[1]), overrides=argv[2:])


@pytest.mark.parametrize("args, said", [
    (["--param", "shape.name=1:2"], "unknown built-in 3D shape 1.0;"),
    (["shape.name=cube"], "unknown built-in 3D shape 'cube'"),
])
def test_a_shape_that_cannot_be_built_is_refused_before_any_trial(tmp_path, capsys, tune_script, args, said):
    """The audit's case: ``--param shape.name=1:2`` ran every trial to ``unknown built-in 3D shape 1.46...`` and
    ended ``every trial failed`` (exit 1), the whole budget spent: the option checks before the trials build no
    shape. A bad shape name given as an override was the same."""
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "1", "--out", str(tmp_path / "study"), *args, *TINY])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith(f"error: the study's shape cannot be built: {said}"), err
    assert err.rstrip().endswith("every trial would fail alike")
    assert ("a study draws numbers, so tune a numeric shape option" in err) == ("--param" in args)
    assert not (tmp_path / "study").exists()


def test_a_tuned_option_given_twice_is_refused_before_any_trial(tmp_path, capsys, tune_script):
    """``--param K=1e-4:1 --param K=1e-3:1``: before, Optuna's "Inconsistent parameter values" warning per trial and
    one of the ranges used unsaid."""
    param = "solver.priors.tv.weight"
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "1", "--out", str(tmp_path / "study"), "--param", f"{param}=1e-4:1",
                          "--param", f"{param}=1e-3:1", *TINY])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err == f"error: --param {param} is given more than once: give each tuned " \
        "option one range\n", err
    assert not (tmp_path / "study").exists()


def test_a_range_of_negative_prior_weights_or_a_bad_range_is_refused_with_its_reason(tmp_path, capsys, tune_script):
    """``--param solver.priors.tv.weight=-1:1:linear``: before, the study ran, every trial drawing a negative weight
    failing alike; ``--param solver.lr=1:0.1`` (or ``=0:1`` on the log scale) said only "invalid parse value"."""
    argv = ["--trials", "2", "--out", str(tmp_path / "study")]
    with pytest.raises(SystemExit) as exit_:
        tune_script.main([*argv, "--param", "solver.priors.tv.weight=-1:1:linear"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == "error: solver.priors.tv.weight: prior 'tv' has a negative weight -1.0\n"
    for text in ("solver.lr=1:0.1", "solver.priors.tv.weight=0:1"):
        with pytest.raises(SystemExit) as exit_:
            tune_script.main([*argv, "--param", text])
        assert exit_.value.code == 2
        assert capsys.readouterr().err.endswith(f"error: argument --param: {text!r}: need LOW < HIGH (and LOW > 0 on a "
                                                "log scale)\n")
    assert not (tmp_path / "study").exists()


def test_a_negative_number_of_random_trials_is_refused_before_any_trial(tmp_path, capsys, tune_script):
    """``--startup-trials -1`` was accepted and the study ran (Optuna took it for none)."""
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "2", "--startup-trials", "-1", "--out", str(tmp_path / "study")])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == ("error: n_startup_trials must be a whole number of random trials >= 0 "
                                       "(tune.py --startup-trials), got -1\n")
    assert not (tmp_path / "study").exists()


def test_without_the_sweeps_extra_one_line_names_it(tmp_path, capsys, monkeypatch, tune_script):
    """Without optuna, tune.py printed a 27-line traceback and exited 1."""
    monkeypatch.setitem(sys.modules, "optuna", None)  # as if the `sweeps` extra were not installed
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "1", "--out", str(tmp_path / "study")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: tuning (scripts/tune.py) needs optuna") and 'pip install "dipnet[sweeps]"' in err


def test_a_recorded_source_without_ground_truth_is_refused_before_any_trial(tmp_path, capsys, tune_script):
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "2", "--out", str(tmp_path / "study"), "source=recorded",
                          f"source.reader.path={CATS_CSV}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: source=recorded: {CATS_CSV} has no ground truth") and "source=simulated" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "study").exists()


def test_a_fake_rig_scan_names_its_ground_truth_and_can_be_tuned_on(tmp_path):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        scan_cfg = compose(config_name="scan", overrides=["n_dips=4", "protocol.step_mm=8", "fsync=false",
                                                          "progress=false", "rig.fake.shape.name=ball"])
    scan_from_config(scan_cfg, tmp_path / "rawscan.jsonl")
    tuning.check_study(2, tuning.DEFAULT_PARAMS,
                       ["source=recorded", f"source.reader.path={tmp_path / 'rawscan.jsonl'}"])


@pytest.fixture
def fake_jobs(monkeypatch):
    """Trials without a reconstruction: each job "scores" the next of ``metrics`` (default: Chamfer 0.1)."""
    metrics: list[dict] = []

    def fake_run(cfg, out):
        return SimpleNamespace(metrics=metrics.pop(0) if metrics else {"chamfer": 0.1, "empty": False})

    monkeypatch.setattr(tuning, "run", fake_run)
    return metrics


def test_an_out_holding_another_study_is_refused_before_any_trial(tmp_path, capsys, fake_jobs, tune_script):
    """Before: a second study into the same --out overwrote best.yaml and trial 0 and left trial 1 beside them."""
    out = tmp_path / "study"
    assert tune_script.main(["--trials", "2", "--out", str(out), *TINY]) == 0
    best = (out / "best.yaml").read_text()
    capsys.readouterr()
    fake_jobs.append({"chamfer": 0.5, "empty": False})  # a trial that ran would take it
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "1", "--seed", "7", "--out", str(out),
                          "--param", "solver.priors.tv.weight=0.5:0.9", *TINY])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith(f"error: --out {out} already holds a study (2 trial folders)")
    assert "another --out" in err and "delete" in err and "--storage" in err
    assert fake_jobs and (out / "best.yaml").read_text() == best


def test_a_study_in_a_storage_goes_on_in_its_out(tmp_path, capsys, fake_jobs, tune_script):
    out, storage = tmp_path / "study", f"sqlite:///{tmp_path / 'optuna.db'}"
    assert tune_script.main(["--trials", "2", "--out", str(out), "--storage", storage, *TINY]) == 0
    fake_jobs.append({"chamfer": 0.05, "empty": False})
    assert tune_script.main(["--trials", "1", "--out", str(out), "--storage", storage, *TINY]) == 0
    assert tuning.study_trial_numbers(out) == [0, 1, 2]
    best = OmegaConf.load(out / "best.yaml")
    assert (best.trials, best.trial, best.chamfer) == (3, 2, 0.05)
    # the same folder with a new storage (its trials would start at 0 again) is another study
    with pytest.raises(SystemExit):
        tune_script.main(["--trials", "1", "--out", str(out), "--storage", f"sqlite:///{tmp_path / 'new.db'}", *TINY])
    assert "already holds a study (3 trial folders)" in capsys.readouterr().err


@pytest.mark.parametrize("changed", [["resolution=12", *TINY[1:]], ["--param", "solver.lr=0.01:0.3", *TINY]])
def test_a_stored_study_continued_with_other_overrides_or_options_is_refused(tmp_path, capsys, fake_jobs, tune_script,
                                                                              changed):
    """Before: the new run's trials were ranked with the stored ones (another grid, other tuned options), exit 0, and
    best.yaml named a stored trial's options under the new run's overrides."""
    out, storage = tmp_path / "study", f"sqlite:///{tmp_path / 'optuna.db'}"
    assert tune_script.main(["--trials", "2", "--out", str(out), "--storage", storage, *TINY]) == 0
    best = (out / "best.yaml").read_text()
    capsys.readouterr()
    fake_jobs.append({"chamfer": 0.01, "empty": False})  # a trial that ran would take it
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "1", "--out", str(out), "--storage", storage, *changed])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: --storage study 'dipnet_prior_weights' was run with other settings (")
    assert "--study-name" in err and fake_jobs and tuning.study_trial_numbers(out) == [0, 1]
    assert (out / "best.yaml").read_text() == best


def test_an_empty_reconstruction_is_never_the_best(tmp_path, capsys, fake_jobs, tune_script):
    """Before: a study whose only trial reconstructed nothing printed 'best chamfer 1.00000' and exit 0."""
    fake_jobs.append({"chamfer": 1.0, "empty": True})
    assert tune_script.main(["--trials", "1", "--out", str(tmp_path / "empty"), *TINY]) == 1
    captured = capsys.readouterr()
    assert "best chamfer" not in captured.out and len(captured.err.splitlines()) == 1, captured.err
    assert captured.err.startswith("error: no best options: every trial's reconstruction is empty")
    assert not (tmp_path / "empty" / "best.yaml").exists()

    fake_jobs.extend([{"chamfer": 1.0, "empty": True}, {"chamfer": 1.0, "empty": False}])
    assert tune_script.main(["--trials", "2", "--out", str(tmp_path / "mixed"), *TINY]) == 0
    assert OmegaConf.load(tmp_path / "mixed" / "best.yaml").trial == 1


def _verdict(chamfer: float, verdict: str, finding: str = "") -> dict:
    """A fake job's metrics with its consistency verdict (and one finding when inconsistent)."""
    return {"chamfer": chamfer, "empty": False, "consistency": verdict,
            "consistency_warnings": [finding] if finding else []}


RATIO = "the reconstruction holds 1.426e+05 mm^3, the dips measure 1.22e+05 mm^3 (ratio 1.168, noise explains +-0.000)"


def test_an_inconsistent_trial_ranks_behind_a_consistent_one_and_best_yaml_says_so(tmp_path, capsys, caplog,
                                                                                   fake_jobs, tune_script):
    """Before: the trial of lowest Chamfer was the best whatever its verdict, and best.yaml said nothing of it (trial
    0 of a 16^3 study: volume ratio 1.168, inconsistent)."""
    fake_jobs.extend([_verdict(0.0075, "inconsistent", RATIO), _verdict(0.0140, "consistent"),
                      _verdict(0.0120, "inconsistent", RATIO)])
    out = tmp_path / "study"
    with caplog.at_level("INFO", logger="dipnet.jobs.tuning"):
        assert tune_script.main(["--trials", "3", "--out", str(out), *TINY]) == 0
    best = OmegaConf.load(out / "best.yaml")
    assert (best.trial, best.chamfer, best.consistency, best.consistent_trials) == (1, 0.014, "consistent", 1)
    assert best.lowest_chamfer.trial == 0 and best.lowest_chamfer.consistency == "inconsistent"
    assert list(best.lowest_chamfer.consistency_warnings) == [RATIO] and "consistent trials first" in best.ranking
    assert "best chamfer 0.01400 (trial 1, consistent)" in capsys.readouterr().out
    assert "trial 0 has a lower Chamfer distance (0.00750 against 0.01400) but is inconsistent with its dips, so it " \
           "ranks behind trial 1 (consistent)" in caplog.text
    assert "trial 0: chamfer 0.00750 (inconsistent)" in caplog.text


def test_a_best_trial_inconsistent_with_its_dips_is_named_with_a_warning(tmp_path, capsys, caplog, fake_jobs,
                                                                         tune_script):
    fake_jobs.extend([_verdict(0.02, "inconsistent", "a finding"), _verdict(0.01, "inconsistent", RATIO)])
    out = tmp_path / "study"
    with caplog.at_level("INFO", logger="dipnet.jobs.tuning"):
        assert tune_script.main(["--trials", "2", "--out", str(out), *TINY]) == 0
    best = OmegaConf.load(out / "best.yaml")
    assert (best.trial, best.consistency, list(best.consistency_warnings)) == (1, "inconsistent", [RATIO])
    assert "lowest_chamfer" not in best and best.consistent_trials == 0
    assert "(trial 1, inconsistent)" in capsys.readouterr().out
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and warned[0].startswith(f"the best trial 1 is inconsistent with its dips ({RATIO}); no "
                                                     "trial of the study is consistent"), warned


def test_a_study_stored_without_verdicts_keeps_ranking_by_chamfer(tmp_path, fake_jobs):
    """Trials that record no verdict (a job without one, a study stored before verdicts were kept) are not held
    against: the lowest Chamfer is the best."""
    fake_jobs.extend([{"chamfer": 0.05, "empty": False}, _verdict(0.08, "consistent")])
    tuning.tune(tmp_path, n_trials=2, overrides=TINY)
    best = OmegaConf.load(tmp_path / "best.yaml")
    assert (best.trial, best.consistency) == (0, None) and "lowest_chamfer" not in best


@pytest.mark.parametrize("value, param, end", [
    (1.1e-4, Param("w", 1e-4, 1.0), "low"),        # 1% of the 4 decades from the low end
    (0.9, Param("w", 1e-4, 1.0), "high"),
    (1e-2, Param("w", 1e-4, 1.0), None),
    (0.52, Param("f", 0.5, 0.95, False), "low"),   # 4% of the linear range
    (0.6, Param("f", 0.5, 0.95, False), None),
])
def test_a_value_at_an_end_of_its_range_is_told_from_one_inside_it(value, param, end):
    assert tuning.range_edges({param.key: value}, [param]) == ({param.key: end} if end else {})


def test_a_best_value_at_the_end_of_its_range_is_named_not_called_the_optimum(tmp_path, capsys, caplog, monkeypatch,
                                                                             tune_script):
    """A study whose Chamfer keeps falling toward one end of the tuned range reported the last value before that end
    as "best" without a word: the search ran into the range's edge, and the optimum may lie beyond it."""
    monkeypatch.setattr(tuning, "run", lambda cfg, out: SimpleNamespace(
        metrics={"chamfer": float(cfg.solver.priors.tv.weight), "empty": False}))   # the lower, the better
    out = tmp_path / "study"
    with caplog.at_level("WARNING", logger="dipnet.jobs.tuning"):
        assert tune_script.main(["--trials", "12", "--startup-trials", "4", "--out", str(out),
                                 "--param", "solver.priors.tv.weight=1e-4:1", *TINY]) == 0
    best = OmegaConf.load(out / "best.yaml")
    weight = best.params["solver.priors.tv.weight"]
    assert tuning.range_edges({"solver.priors.tv.weight": weight}, [Param("solver.priors.tv.weight", 1e-4, 1.0)])
    edge = best.at_range_edge["solver.priors.tv.weight"]
    assert edge.end == "low" and list(edge.range) == [1e-4, 1.0] and edge.scale == "log"
    assert "solver.priors.tv.weight at the low end of its range" in capsys.readouterr().out
    assert any("lies at the low end of its range [0.0001, 1]" in r.getMessage() and "--param "
               "solver.priors.tv.weight=1e-05:1" in r.getMessage() for r in caplog.records), caplog.text


def test_a_range_whose_high_end_the_option_refuses_is_refused_before_any_trial(tmp_path, capsys, tune_script):
    """``--param snr_db=10:300:linear``: only the low end was checked; every trial drawn above 200 dB failed."""
    with pytest.raises(SystemExit) as exit_:
        tune_script.main(["--trials", "2", "--out", str(tmp_path / "study"), "--param", "snr_db=10:300:linear", *TINY])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: snr_db must be a number of dB in [-20, 200]") and "high end of a tuned range" in err
    assert not (tmp_path / "study").exists()


def test_an_integer_option_is_tuned_in_whole_numbers(tmp_path, monkeypatch):
    """``tune.py --param n_dips=5:50`` was refused: "n_dips must be a positive integer, got 5.0" (every value drawn
    was a float). An integer option with whole ends is drawn by ``suggest_int``; a float option stays a float."""
    received = []

    def fake_run(cfg, out):
        received.append((cfg.n_dips, cfg.solver.iterations, cfg.solver.priors.tv.weight))
        return SimpleNamespace(metrics={"chamfer": 0.1, "empty": False})

    monkeypatch.setattr(tuning, "run", fake_run)
    params = [Param.parse("n_dips=5:50"), Param.parse("solver.iterations=10:20:linear"),
              Param.parse("solver.priors.tv.weight=1:10")]
    tuning.check_study(3, params, ["resolution=16"])
    study = tuning.tune(tmp_path / "study", n_trials=3, params=params, overrides=["resolution=16"])
    assert len(received) == 3 and [t.state.name for t in study.trials] == ["COMPLETE"] * 3
    for n_dips, iterations, weight in received:
        assert type(n_dips) is int and 5 <= n_dips <= 50 and type(iterations) is int and 10 <= iterations <= 20
        assert type(weight) is float and 1 <= weight <= 10
