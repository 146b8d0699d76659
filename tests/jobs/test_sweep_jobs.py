"""Sweep jobs (dipnet.jobs.sweep_jobs): a failing job writes error.txt and returns None; Ctrl-C still stops; the
Hydra callback logs one short line per job and the failures at the end."""

import logging
from pathlib import Path

import pytest
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from dipnet.experiments import collect
from dipnet.jobs import sweep_jobs
from dipnet.jobs.sweep_jobs import ERROR_FILE, guarded_job

from script_runs import run_script
from sweep_fixtures import chamfer_of, write_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return write_sweep(tmp_path_factory.mktemp("sweep"))


def test_a_finished_job_returns_its_value(tmp_path):
    assert guarded_job(lambda: 0.25, tmp_path) == 0.25
    assert not (tmp_path / ERROR_FILE).exists()


def test_a_failed_job_writes_its_error_and_returns_none(tmp_path):
    def fail():
        raise ValueError("resolution must be\n an integer")

    assert guarded_job(fail, tmp_path / "job") is None
    text = (tmp_path / "job" / ERROR_FILE).read_text()
    assert text.startswith("ValueError: resolution must be an integer\n\n") and "Traceback" in text
    assert guarded_job(lambda: (_ for _ in ()).throw(SystemExit(2)), tmp_path / "exit") is None


def test_ctrl_c_is_not_swallowed(tmp_path):
    def interrupt():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        guarded_job(interrupt, tmp_path)


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

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"):   # a single run: its own "done:" line
        callback.on_job_end(_hydra_cfg(sweep / "0", None), ok)
    assert "done [" not in caplog.text

    out = tmp_path / "crashed"
    out.mkdir()
    failed = JobReturn(overrides=["n_dips=-1"], status=JobStatus.FAILED)
    failed.return_value = RuntimeError("solver diverged")
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"):
        callback.on_job_end(_hydra_cfg(out, 7), failed)
    assert "job 7 FAILED [n_dips=-1]: solver diverged" in caplog.text
    assert (out / "error.txt").read_text().startswith("RuntimeError: solver diverged")

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="dipnet.jobs.sweep_jobs"), pytest.raises(SystemExit) as exit_:
        callback.on_multirun_end(_hydra_cfg(sweep / "0", 0, sweep))
    n = len(collect.collect_runs(sweep))
    assert f"sweep finished: {n - 3} of {n} jobs ok" in caplog.text and exit_.value.code == 1
    assert "ValueError: n_dips too large" in caplog.text and "scripts/compare.py" in caplog.text


def test_a_sweep_into_the_folder_of_an_earlier_sweep_is_refused(sweep, tmp_path, capsys):
    """Before: the new jobs replaced the earlier ones of the same numbers, the others stayed beside them, and
    'sweep finished' counted both sweeps' jobs."""
    callback = sweep_jobs.JobLogCallback()
    n = len(collect.collect_runs(sweep))
    with pytest.raises(SystemExit) as exit_:  # not an exception: Hydra would only warn and run the sweep
        callback.on_multirun_start(_hydra_cfg(sweep / "0", 0, sweep))
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith(f"error: hydra.sweep.dir={sweep} already holds another sweep ({n} jobs): ")
    assert "another hydra.sweep.dir" in err and "delete" in err

    # a new folder, an empty one, or one whose sweep failed before its first job (a bad override: Hydra wrote
    # only multirun.yaml) takes the sweep: it holds nothing to keep (the corrected command was refused before)
    failed = tmp_path / "failed"
    failed.mkdir()
    (failed / "multirun.yaml").write_text("hydra:\n  overrides:\n    task: ['solver.threshold=0.5,0.9']\n")
    for fresh in (tmp_path / "new", tmp_path / "empty", failed):
        if fresh.name == "empty":
            fresh.mkdir()
        callback.on_multirun_start(_hydra_cfg(fresh / "0", 0, fresh))


def test_the_same_sweep_run_again_goes_into_its_own_folder(tmp_path):
    """Re-running a sweep's command (the same task overrides in its multirun.yaml) is let through, so jobs with
    output.checkpoint resume; a sweep with other overrides into that folder is refused."""
    callback = sweep_jobs.JobLogCallback()
    done = tmp_path / "sweep"
    (done / "0").mkdir(parents=True)
    (done / "multirun.yaml").write_text("hydra:\n  overrides:\n    task: ['solver=minnorm,voxel', 'n_dips=8']\n")
    again = OmegaConf.merge(_hydra_cfg(done / "0", 0, done),
                            {"hydra": {"overrides": {"task": ["solver=minnorm,voxel", "n_dips=8"]}}})
    callback.on_multirun_start(again)
    other = OmegaConf.merge(again, {"hydra": {"overrides": {"task": ["solver=lsqr", "n_dips=8"]}}})
    with pytest.raises(SystemExit):
        callback.on_multirun_start(other)


def test_a_sweep_with_a_failed_job_exits_1(tmp_path, monkeypatch, capsys):
    """``reconstruct.py -m solver=voxel_learned,minnorm resolution=16 n_dips=8`` (the learned prior's weights are
    for 64^3, so that job fails): before, exit 0 after "sweep finished: 1 of 2 jobs ok", and exit 0 when every job
    failed ("0 of 2", then "compare the finished ones with ..."); a script chaining the sweep took it for a
    success. Now the failures are listed as before, then one ``error:`` line and exit 1; a sweep whose jobs all
    finish still exits 0."""
    quick = ["resolution=16", "n_dips=8", "threads=1", "output.progress=false", "output.figures=false",
             "output.uncertainty=false", "output.resolvability=false", "output.mesh_formats=[]"]
    mixed = run_script("reconstruct", "-m", "solver=voxel_learned,minnorm", *quick,
                       f"hydra.sweep.dir={tmp_path / 'mixed'}", monkeypatch=monkeypatch, capsys=capsys)
    assert mixed.returncode == 1 and "sweep finished: 1 of 2 jobs ok" in mixed.stdout, mixed.stderr[-2000:]
    assert mixed.stderr.rstrip().splitlines()[-1] == (
        f"error: 1 of 2 jobs of the sweep in {tmp_path / 'mixed'} failed or did not finish (listed above, each with "
        "its error.txt): the sweep exits 1")
    failed = run_script("reconstruct", "-m", "solver=voxel_learned", "seed=0,1", *quick,
                        f"hydra.sweep.dir={tmp_path / 'failed'}", monkeypatch=monkeypatch, capsys=capsys)
    assert failed.returncode == 1 and "compare the finished ones" not in failed.stdout + failed.stderr
    ok = run_script("reconstruct", "-m", "solver=minnorm", "seed=0,1", *quick, f"hydra.sweep.dir={tmp_path / 'ok'}",
                    monkeypatch=monkeypatch, capsys=capsys)
    assert ok.returncode == 0 and "sweep finished: 2 of 2 jobs ok" in ok.stdout, ok.stderr[-2000:]


QUICK = ["resolution=12", "threads=1", "solver=minnorm", "output.progress=false", "output.figures=false",
         "output.uncertainty=false", "output.resolvability=false", "output.mesh_formats=[]"]


def test_a_sweep_preset_run_without_m_says_it_runs_one_job(tmp_path, monkeypatch, capsys):
    """``reconstruct.py experiment=dips_sweep`` (no ``-m``): before, one job (n_dips set, shape.name=chamber_box), exit
    0, without a word that the preset's sweep over shape.name was not run. Options set on the command line are
    not named; a sweep (``-m``) says nothing."""
    out = tmp_path / "run"
    done = run_script("reconstruct", "experiment=dips_sweep", "n_dips=8", *QUICK, f"hydra.run.dir={out}",
                      monkeypatch=monkeypatch, capsys=capsys)
    assert done.returncode == 0, done.stderr[-2000:]
    assert ("experiment=dips_sweep sweeps shape.name=chamber_box,torus,box only with -m: this single run ignores "
            "that and runs one job with shape.name=chamber_box; add -m") in (out / "reconstruct.log").read_text()
    cfg = OmegaConf.create({"n_dips": 8, "shape": {"name": "torus"}})
    hydra = {"mode": "RUN", "sweeper": {"params": {"n_dips": "10,20", "shape.name": "torus,box"}},
             "runtime": {"choices": {"experiment": "dips_sweep"}}, "overrides": {"task": ["shape.name=torus"]}}
    assert "n_dips=10,20 only with -m" in sweep_jobs.unswept_params(OmegaConf.create(hydra), cfg)
    hydra["overrides"]["task"].append("n_dips=8")
    assert sweep_jobs.unswept_params(OmegaConf.create(hydra), cfg) is None
    assert sweep_jobs.unswept_params(OmegaConf.create({**hydra, "mode": "MULTIRUN"}), cfg) is None
    assert sweep_jobs.unswept_params(OmegaConf.create({"mode": "RUN", "sweeper": {"params": None}}), cfg) is None


def _cut_job(sweep: Path, num: int, task: list[str], sweep_task: list[str], launch: tuple[str, ...] = ()):
    """The Hydra config of sweep job ``num`` (``HydraConfig.get()`` in the job) and the sweep's ``multirun.yaml``."""
    hydra = {"mode": "MULTIRUN", "sweep": {"dir": str(sweep), "subdir": "${hydra.job.num}"},
             "sweeper": {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper", "params": None},
             "launcher": {"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"},
             "runtime": {"output_dir": str(sweep / str(num))}, "job": {"num": num, "config_name": "config"},
             "overrides": {"task": task, "hydra": [f"hydra.sweep.dir={sweep}", "hydra.mode=MULTIRUN", *launch]}}
    sweep.mkdir(parents=True, exist_ok=True)
    saved = {"hydra": {**hydra, "overrides": {**hydra["overrides"], "task": sweep_task}}}
    OmegaConf.save(OmegaConf.create(saved), sweep / "multirun.yaml")
    return OmegaConf.create(hydra)


def test_a_cut_sweep_job_says_how_to_resume_it_alone_and_how_to_finish_the_sweep(tmp_path, monkeypatch):
    """Before: "rerun the same command with hydra.run.dir=SWEEP/1 to resume the solve from its checkpoint"; a sweep
    ignores hydra.run.dir, so that reran the whole sweep (and without hydra.sweep.dir, into a new dated folder)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from script_modules import load_script

    sweep = tmp_path / "my sweep"
    hydra_cfg = _cut_job(sweep, 1, ["solver=voxel", "n_dips=12", "shape.path=${dipnet_data:meshes/hand.ply}"],
                         ["solver=voxel", "n_dips=6,12,18", "shape.path=${dipnet_data:meshes/hand.ply}"],
                         ("hydra/job_logging=disabled",))
    reconstruct = load_script("reconstruct")
    monkeypatch.setattr(HydraConfig, "initialized", staticmethod(lambda: True))
    monkeypatch.setattr(HydraConfig, "get",
                        staticmethod(lambda: OmegaConf.merge(hydra_cfg, {"mode": RunMode.MULTIRUN})))
    cfg = OmegaConf.create({"output": {"checkpoint": True}})
    hint = reconstruct.resume_hint(cfg, sweep / "1")
    single = (f"python scripts/reconstruct.py solver=voxel n_dips=12 'shape.path=${{dipnet_data:meshes/hand.ply}}' "
              f"hydra/job_logging=disabled 'hydra.run.dir={sweep}/1'")
    again = (f"python scripts/reconstruct.py -m solver=voxel n_dips=6,12,18 "
             f"'shape.path=${{dipnet_data:meshes/hand.ply}}' hydra/job_logging=disabled 'hydra.sweep.dir={sweep}'")
    assert hint == (f"sweep job 1 ({sweep}/1) was cut: its solve resumes from its checkpoint (output.checkpoint). A "
                    f"sweep ignores hydra.run.dir; to rerun this job alone, run it once into its folder: {single}. "
                    f"Job 2 of the sweep's 3 did not start: to finish the sweep, run it again into its folder: "
                    f"{again} (it runs every job again, the finished ones and this one from their checkpoints)")
    no_checkpoint = reconstruct.resume_hint(OmegaConf.create({"output": {"checkpoint": None}}), sweep / "1")
    assert "nothing of its solve was kept" in no_checkpoint and no_checkpoint.endswith("each from the start)")
    # the last job: that run finishes the sweep; a parallel launcher: which jobs finished is not known
    last = sweep_jobs.sweep_resume_hint(_cut_job(sweep, 2, ["n_dips=18"], ["n_dips=6,12,18"]), True)
    assert last.endswith(f"hydra.run.dir={sweep}/2'. It is the sweep's last job (of 3): that run finishes the sweep")
    parallel = _cut_job(sweep, 0, ["n_dips=6"], ["n_dips=6,12,18"], ("hydra/launcher=joblib",))
    OmegaConf.save(OmegaConf.merge(OmegaConf.load(sweep / "multirun.yaml"),
                                   {"hydra": {"launcher": {"_target_": "hydra_plugins.JoblibLauncher"}}}),
                   sweep / "multirun.yaml")
    assert ". To finish the sweep (its jobs after this one, or those that had not finished), run it again into its " \
           f"folder: python scripts/reconstruct.py -m n_dips=6,12,18 hydra/launcher=joblib 'hydra.sweep.dir={sweep}'" \
           in sweep_jobs.sweep_resume_hint(parallel, True)
    (sweep / "multirun.yaml").unlink()  # no record of the sweep: the single run alone
    assert sweep_jobs.sweep_resume_hint(hydra_cfg, True).endswith(single)
