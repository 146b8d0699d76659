"""Training the learned prior: batches, determinism by seed, resume = uninterrupted."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings

import pytest
import torch

from dipnet.experiments.prior_training import STAGE2, TrainConfig, TrainConfigError, random_batch, same_run, train
from dipnet.preprocessing.datasets import MESHES_DIR
from dipnet.solvers.denoiser import SHIPPED_DIR, OccupancyDenoiser, PriorWeightsError, load_weights, save_weights

from script_modules import load_script

TINY = TrainConfig(train_seeds=(5000, 5002), val_seeds=(5002, 5003), n=16, dips=8, solver_iterations=10, channels=2,
                   steps=6, batch=2, crop=8, checkpoint_every=3)


def test_batches_flip_and_permute_input_and_target_alike():
    vol = torch.arange(16.0**3).reshape(1, 16, 16, 16)
    x, y = random_batch(vol, vol * 2, 3, 8, torch.Generator().manual_seed(0))
    assert x.shape == (3, 1, 8, 8, 8) and torch.equal(y, 2 * x)


def test_training_is_deterministic_and_resume_continues_the_same_run(tmp_path, shared_pairs):
    cache = tmp_path / "pairs"
    meta = train(TINY, tmp_path / "a.pt", cache, progress=False)
    assert meta["steps_done"] == 6 and meta["config"]["seed"] == 0
    stopped = train(dataclasses.replace(TINY, max_minutes=0.0), tmp_path / "b.pt", cache, progress=False)
    assert stopped["steps_done"] == 1  # out of time after its first step, between checkpoints (every 3)
    resumed = train(TINY, tmp_path / "b.pt", cache, resume=True, progress=False)
    assert resumed["steps_done"] == 6
    a, _ = load_weights(tmp_path / "a.pt")
    b, _ = load_weights(tmp_path / "b.pt")
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(p, q), name


def test_a_stopped_run_started_again_without_resume_is_refused_before_its_checkpoint_is_replaced(tmp_path,
                                                                                                  shared_pairs):
    """The same command without ``--resume`` after a ``max_minutes`` stop (or a kill) trained from step 0 and
    replaced the checkpoint's steps at its first one; now it is refused, the checkpoint left as it was."""
    cache, out = tmp_path / "pairs", tmp_path / "w.pt"
    train(dataclasses.replace(TINY, max_minutes=0.0), out, cache, progress=False)
    before = out.with_suffix(".ckpt").read_bytes()
    with pytest.raises(TrainConfigError, match=r"holds this run stopped at step 1 of 6: .*add --resume"):
        train(TINY, out, cache, progress=False)
    assert out.with_suffix(".ckpt").read_bytes() == before
    assert train(TINY, out, cache, resume=True, progress=False)["steps_done"] == 6
    assert train(TINY, out, cache, progress=False)["steps_done"] == 6  # a finished run may be made again


def test_a_checkpoint_older_than_a_config_field_resumes_with_its_default():
    """A checkpoint written before ``noise_model`` existed was an ``independent`` run."""
    saved = dataclasses.asdict(TINY)
    del saved["noise_model"]
    assert same_run(saved, TINY)
    assert same_run(saved | {"steps": 3, "max_minutes": 1.0}, TINY)  # a resumed run may go on longer
    assert not same_run(saved, dataclasses.replace(TINY, noise_model="correlated"))
    assert not same_run(saved | {"seed": 1}, TINY)


def test_the_noise_model_of_the_noisy_pairs_is_part_of_the_config(tmp_path, shared_pairs):
    """``noise_model="correlated"`` makes the noisy pairs afresh with it and reuses the noise-free ones."""
    cache = tmp_path / "pairs"
    train(dataclasses.replace(TINY, steps=1), tmp_path / "a.pt", cache, progress=False)
    assert len(list(cache.glob("pair_*.npz"))) == 6  # three seeds, two noise levels
    meta = train(dataclasses.replace(TINY, steps=1, noise_model="correlated"), tmp_path / "b.pt", cache, progress=False)
    assert len(list(cache.glob("pair_*.npz"))) == 9 and meta["config"]["noise_model"] == "correlated"
    args = load_script("train_prior").parse_args(["--noise-model", "correlated"])
    assert args.noise_model == "correlated"


def test_a_second_stage_starts_from_the_given_weights_on_refined_inputs(tmp_path, shared_pairs):
    """``init_weights`` + ``refine``: the run continues the given network (at a vanishing learning rate
    it stays the same) on second-stage inputs, and its meta says so; a network of another width is refused."""
    cache = tmp_path / "pairs"
    train(TINY, tmp_path / "first.pt", cache, progress=False)
    refine = {"iterations": 5, "coarse_to_fine": False, "priors": {"tv": {"weight": 1e-3}}}
    second = dataclasses.replace(TINY, init_weights=str(tmp_path / "first.pt"), refine=refine, lr=1e-12, steps=3)
    meta = train(second, tmp_path / "second.pt", cache, progress=False)
    assert meta["config"]["init_weights"] == str(tmp_path / "first.pt") and "second stage" in meta["trained_on"]
    # three seeds (two to train on, one to validate), two noise levels
    assert len(list(cache.glob("stage2_*.npz"))) == 6
    a, _ = load_weights(tmp_path / "first.pt")
    b, _ = load_weights(tmp_path / "second.pt")
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.allclose(p, q, atol=1e-8), name
    with pytest.raises(ValueError, match="channels"):
        train(dataclasses.replace(second, channels=4), tmp_path / "wide.pt", cache, progress=False)


def test_the_script_makes_the_second_stage_from_one_round_of_voxel_learned():
    script = load_script("train_prior")
    args = script.parse_args(["--stage", "2"])
    assert (args.init_weights, args.steps, args.lr) == (STAGE2["init_weights"], STAGE2["steps"], STAGE2["lr"])
    assert args.out.name == "denoiser64_stage2.pt" and script.parse_args([]).init_weights is None
    refine = script.learned_round()
    assert refine["rounds"] == refine["min_rounds"] == 1 and "warm_start" not in refine and "later_priors" not in refine
    assert "threshold" not in refine  # the binary level leaves the occupancy, and the pairs' cache key, alone
    assert "surface_refit" not in refine  # so does the surface refit (a mesh beside the occupancy)
    assert refine["priors"]["learned"]["mode"] == "anchor" and refine["priors"]["learned"]["weights"] is None


def test_the_second_stage_round_is_the_one_that_made_the_shipped_weights():
    script = load_script("train_prior")
    shipped = json.loads((SHIPPED_DIR / "denoiser64_stage2.json").read_text())["config"]["refine"]
    assert script.learned_round() == shipped  # the default round is the one recorded with the weights
    assert script.parse_args(["--stage", "2", "--refine-temperature", "0.125"]).refine_temperature == 0.125
    assert script.learned_round(0.125)["temperature_end"] == 0.125
    assert (script.refine_of(script.parse_args(["--stage", "2"])) == shipped
            and script.refine_of(script.parse_args([])) is None)


@pytest.mark.parametrize("stage", [1, 2])
def test_the_shipped_weights_are_the_scripts_recipe_with_their_seed(stage):
    """The defaults of ``train_prior.py`` (``--stage 2``: fine-tuning the shipped first stage) with the
    recorded ``--seed`` are the run that made each shipped file (up to its ``max_minutes``)."""
    script = load_script("train_prior")
    name = "denoiser64" if stage == 1 else "denoiser64_stage2"
    saved = json.loads((SHIPPED_DIR / f"{name}.json").read_text())["config"]
    saved |= {"train_seeds": tuple(saved["train_seeds"]), "val_seeds": tuple(saved["val_seeds"])}
    assert same_run(saved, script.config_of(script.parse_args(["--stage", str(stage), "--seed", str(saved["seed"])])))


def test_a_new_cascade_refines_with_its_own_first_stage_and_noise_model():
    script = load_script("train_prior")
    args = script.parse_args(["--stage", "2", "--init-weights", "d1.pt", "--noise-model", "correlated"])
    refine = script.refine_of(args)
    assert refine["priors"]["learned"]["weights"] == "d1.pt"
    assert refine["noise_model"] == "correlated" and refine["white_share"] > 0
    assert "noise_model" not in script.learned_round()  # the shipped round: independent slabs


def test_family_seeds_add_training_shapes_of_a_named_family(tmp_path, shared_pairs):
    """``--family-seeds organic A B`` trains on the seeds' own pairs plus organic ones, and says so."""
    script = load_script("train_prior")
    config = script.config_of(script.parse_args(["--family-seeds", "organic", "5003", "5004"]))
    assert config.family_seeds == {"organic": (5003, 5004)}
    for bad in (["blobby", "1", "2"], ["organic", "5", "5"], ["organic", "a", "2"]):
        with pytest.raises(ValueError, match="--family-seeds"):
            script.config_of(script.parse_args(["--family-seeds", *bad]))
    meta = train(dataclasses.replace(TINY, steps=1, family_seeds={"organic": (5003, 5004)}), tmp_path / "a.pt",
                 tmp_path / "pairs", progress=False)
    assert len(list((tmp_path / "pairs").glob("pair_*.npz"))) == 8  # 3 seeds' own + 1 organic, 2 noise levels
    assert meta["trained_on"].endswith("organic seeds 5003..5003")


def test_meshes_add_training_shapes_under_random_rotations(tmp_path, shared_pairs):
    """``--meshes FILE --mesh-seeds A B`` trains on the seeds' pairs plus the mesh's turned copies, names
    the file and its digest in ``trained_on``, and refuses a missing or repeated file or an empty range."""
    import trimesh

    mesh = tmp_path / "box.ply"
    trimesh.creation.box(extents=(2.0, 1.0, 0.5)).export(mesh)
    script = load_script("train_prior")
    config = script.config_of(script.parse_args(["--meshes", str(mesh), "--mesh-seeds", "3", "5"]))
    assert config.meshes == (str(mesh),) and config.mesh_seeds == (3, 5)
    for bad in (["--meshes", str(tmp_path / "none.ply")], ["--meshes", str(mesh), str(mesh)],
                ["--meshes", str(mesh), "--mesh-seeds", "2", "2"]):
        with pytest.raises(ValueError, match="--mesh"):
            script.config_of(script.parse_args(bad))
    meta = train(dataclasses.replace(TINY, steps=1, meshes=(str(mesh),), mesh_seeds=(3, 4)), tmp_path / "a.pt",
                 tmp_path / "pairs", progress=False)
    assert len(list((tmp_path / "pairs").glob("pair_box-3_*.npz"))) == 2  # noise-free and noisy
    assert "box.ply (" in meta["trained_on"] and meta["trained_on"].endswith("seeds 3..3")


def test_the_second_stage_can_be_fine_tuned_from_itself_with_the_first_stage_round():
    """``--refine-weights`` names the round's first stage apart from the weights trained on."""
    script = load_script("train_prior")
    args = script.parse_args(["--stage", "2", "--init-weights", "denoiser64_stage2", "--refine-weights", "denoiser64"])
    assert script.config_of(args).init_weights == "denoiser64_stage2"
    assert script.refine_of(args) == script.learned_round()  # the shipped first stage's round


@pytest.mark.parametrize("argv, message", [
    (["--n", "0"], "n must be an integer >= 4, got 0"),
    (["--train-seeds", "1005", "1000"], "train_seeds must be FIRST STOP, whole numbers with 0 <= FIRST < STOP"),
    # negative seeds: numpy's "expected non-negative integer" after the training pairs were made
    (["--val-seeds", "-3", "-1"], "val_seeds must be FIRST STOP, whole numbers with 0 <= FIRST < STOP .*got -3 -1"),
    (["--family-seeds", "organic", "-4", "-2"], "family_seeds organic must be FIRST STOP, whole numbers with 0 <="),
    (["--meshes", "{bunny}", "--mesh-seeds", "-2", "0"], "mesh_seeds must be FIRST STOP, whole numbers with 0 <="),
    (["--out", "{tmp}"], "the weights file .* is a folder: give a file"),  # was a traceback after the training
    (["--crop", "64", "--n", "16"], "n and crop must be multiples of 4 .* with crop <= n .*got n=16, crop=64"),
    (["--lr", "nan"], "lr must be a positive, finite learning rate, got nan"),
    (["--steps", "-1"], "steps must be a positive integer, got -1"),
    (["--snr-db", "1e308"], r"snr_db must be a number of dB in \[-20, 200\]"),
    (["--family-seeds", "organic", "5", "5"], "--family-seeds organic 5 5: FIRST and STOP must be whole numbers"),
    (["--meshes", "none.ply"], "--meshes: no such file: none.ply"),
    (["--init-weights", "{tmp}/bad.pt"], r"learned-prior weights .*bad.pt are not a dipnet denoiser weights file"),
    (["--init-weights", "{tmp}/nan.pt"], r"learned-prior weights .*nan.pt: tensor down0.0.weight holds NaN"),
    # stage 2's options at stage 1, --mesh-seeds without --meshes: ignored (first-stage weights written, exit 0)
    (["--refine-temperature", "0.125"], "--refine-temperature set the second stage's round, which stage 1 does not"),
    (["--refine-weights", "denoiser64"], "--refine-weights set the second stage's round, .*add --stage 2"),
    (["--mesh-seeds", "0", "2"], "--mesh-seeds 0 2 sets the rotations of each of --meshes, and no --meshes are given"),
])
def test_bad_options_of_the_script_are_one_line_and_exit_2(tmp_path, capsys, argv, message):
    """Every bad option or weights file: ``error: ...`` in one line, exit code 2, before any pair or weights file."""
    (tmp_path / "bad.pt").write_bytes(b"not weights")
    nan = OccupancyDenoiser(TINY.channels)
    torch.nn.init.constant_(nan.down0[0].weight, float("nan"))
    save_weights(nan, tmp_path / "nan.pt", {"n": 16, "ndim": 3, "n_slabs_per_voxel": 1})
    script = load_script("train_prior")
    argv = [a.format(tmp=tmp_path, bunny=MESHES_DIR / "bunny.ply") for a in argv]
    with pytest.raises(SystemExit) as exit_:
        script.main(["--out", str(tmp_path / "w.pt"), "--cache", str(tmp_path / "pairs"), "--no-progress", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and re.match(f"error: {message}", err), err
    assert not (tmp_path / "w.pt").exists() and not (tmp_path / "pairs").exists()
    assert not list(tmp_path.parent.glob(f"{tmp_path.name}.*"))  # no checkpoint beside an --out folder


@pytest.mark.parametrize("tilt", [0.0, -5.0, 91.0, float("nan")])
def test_a_tilt_limit_outside_0_to_90_degrees_is_refused(tilt):
    with pytest.raises(TrainConfigError, match=r"max_tilt_deg must be a tilt in \(0, 90\] degrees"):
        TrainConfig(max_tilt_deg=tilt)


def test_validation_seeds_that_overlap_the_training_seeds_are_refused():
    """A validation loss on shapes trained on is no held-out score: overlapping ranges are refused (touching ones,
    [1000, 1004) and [1004, 1006), share no seed)."""
    with pytest.raises(TrainConfigError, match=r"val_seeds 1003 1005 share the seeds 1003\.\.1003 with train_seeds "
                                               r"1000 1004: the validation loss would score shapes trained on"):
        TrainConfig(train_seeds=(1000, 1004), val_seeds=(1003, 1005))
    with pytest.raises(TrainConfigError, match=r"share the seeds 1000\.\.1001"):
        TrainConfig(train_seeds=(1000, 1004), val_seeds=(990, 1002))
    TrainConfig(train_seeds=(1000, 1004), val_seeds=(1004, 1006))


def test_a_diverging_training_writes_nothing_and_says_to_lower_the_learning_rate(tmp_path, shared_pairs, capsys):
    """``--lr 1e12``: the validation loss becomes 2.6e+23 (a NaN or infinite one with more channels); one
    ``error:`` line naming the step and ``--lr``, exit 2, and neither weights nor a checkpoint of the diverged
    network: an earlier run's files stay as they were."""
    cache, out = tmp_path / "pairs", tmp_path / "w.pt"
    train(dataclasses.replace(TINY, steps=3), out, cache, progress=False)
    before = {path: path.read_bytes() for path in (out, out.with_suffix(".ckpt"))}
    argv = ["--out", str(out), "--cache", str(cache), "--no-progress", "--lr", "1e12", "--n", "16", "--dips", "8",
            "--solver-iterations", "10", "--channels", "2", "--steps", "6", "--batch", "2", "--crop", "8",
            "--checkpoint-every", "3", "--train-seeds", "5000", "5002", "--val-seeds", "5002", "5003"]
    with pytest.raises(SystemExit) as exit_:
        load_script("train_prior").main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert re.match(r"error: training diverged: the (training|validation) loss became \S+ at step \d of 6 "
                    r"\(lr 1e\+12\); no weights or checkpoint written: try a lower --lr", err), err
    assert all(path.read_bytes() == data for path, data in before.items())


def test_a_damaged_checkpoint_is_not_resumed_training_starts_afresh_with_a_warning(tmp_path, shared_pairs):
    """A checkpoint cut short (a kill mid-write, before writes were atomic) stopped ``--resume`` with
    ``error: [Errno 22] Invalid argument``, naming nothing; now it is named in a warning and the training starts at
    step 0, as an uninterrupted run; no ``.tmp`` is left beside the checkpoints written."""
    cache = tmp_path / "pairs"
    fresh = train(TINY, tmp_path / "a.pt", cache, progress=False)
    train(dataclasses.replace(TINY, steps=3), tmp_path / "b.pt", cache, progress=False)
    ckpt = tmp_path / "b.ckpt"
    ckpt.write_bytes(ckpt.read_bytes()[:ckpt.stat().st_size // 2])
    with pytest.warns(UserWarning, match=r"checkpoint .*b\.ckpt is not used: it is damaged or truncated .*training "
                                         r"from step 0"):
        resumed = train(TINY, tmp_path / "b.pt", cache, resume=True, progress=False)
    assert resumed["steps_done"] == 6 and resumed["validation"] == fresh["validation"]
    with pytest.warns(UserWarning, match=r"--resume: there is no checkpoint .*c\.ckpt .*training from step 0"):
        assert train(TINY, tmp_path / "c.pt", cache, resume=True, progress=False)["steps_done"] == 6
    assert not list(tmp_path.glob("*.tmp"))


def test_a_checkpoint_of_other_options_is_refused_naming_them_before_the_pairs(tmp_path, shared_pairs):
    """``--resume --seed 3 --lr 0.002`` on another run's checkpoint: refused (as before), now naming the options
    that differ instead of printing the recorded config whole, and before any training pair is made."""
    train(dataclasses.replace(TINY, steps=3), tmp_path / "a.pt", tmp_path / "pairs", progress=False)
    other = dataclasses.replace(TINY, seed=3, lr=2e-3, steps=9)
    with pytest.raises(TrainConfigError, match=r"^checkpoint .*a\.ckpt was made with other options \(lr 0\.001 -> "
                                               r"0\.002; seed 0 -> 3 \(recorded -> now\)\): give the same options"):
        train(other, tmp_path / "a.pt", tmp_path / "other_pairs", resume=True, progress=False)
    assert not (tmp_path / "other_pairs").exists()


@pytest.mark.parametrize("weights, error, message", [
    ("{tmp}/cut.pt", PriorWeightsError, r"learned-prior weights .*cut\.pt are unreadable"),
    ("{tmp}/none.pt", PriorWeightsError, r"learned-prior weights not found: .*none\.pt"),
    ("denoiser64", TrainConfigError, r"the second stage's round runs on the pairs' 16\^3 grid, but its weights "
                                     r"denoiser64 \(--refine-weights, or --init-weights\) were trained for 64\^3"),
])
def test_the_second_stage_rounds_weights_are_checked_before_any_pair(tmp_path, weights, error, message):
    """A ``--refine-weights`` file that is cut short, missing or of another grid stopped the second stage only when
    its round first ran, after every first-stage training pair was made (about 20 minutes at 64^3); now before."""
    first = tmp_path / "first.pt"
    save_weights(OccupancyDenoiser(TINY.channels), first, {"n": 16, "ndim": 3, "n_slabs_per_voxel": 1})
    (tmp_path / "cut.pt").write_bytes(first.read_bytes()[:5000])
    refine = {"priors": {"learned": {"weights": weights.format(tmp=tmp_path)}}}
    config = dataclasses.replace(TINY, init_weights=str(first), refine=refine)
    with pytest.raises(error, match=message):
        train(config, tmp_path / "w.pt", tmp_path / "pairs", progress=False)
    assert not (tmp_path / "pairs").exists()


@pytest.mark.parametrize("temperature", [0.0, float("nan"), -1.0])
def test_a_second_stage_round_temperature_it_cannot_run_is_refused_before_any_pair(tmp_path, capsys, temperature):
    """``--stage 2 --refine-temperature nan``: "error: need 0 < temperature_end <= temperature_start", naming no
    option, after every first-stage training pair was made (about 30 minutes at 64^3); now first, naming it."""
    argv = ["--stage", "2", "--refine-temperature", str(temperature), "--out", str(tmp_path / "w.pt"), "--cache",
            str(tmp_path / "pairs"), "--no-progress", "--train-seeds", "5000", "5001", "--val-seeds", "5001", "5002"]
    with pytest.raises(SystemExit) as exit_:
        load_script("train_prior").main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: the second stage's round (at --refine-temperature {temperature!r}) cannot run: ")
    assert not (tmp_path / "pairs").exists()


def test_a_session_stopped_by_max_minutes_says_its_weights_are_unfinished(tmp_path, shared_pairs):
    """``--max-minutes`` (90 by default) ends a session and writes the weights as a finished run does, exit 0: a
    warning says they are those of step 1 of 6 and how to continue. The time is checked after every step: it was
    checked only at checkpoints, so a session ran up to ``checkpoint_every`` steps past its minutes (250 steps,
    about 3 minutes at 64^3) and ``max_minutes=0`` stopped at step 3."""
    with pytest.warns(UserWarning, match=r"training stopped by max_minutes=0 \(--max-minutes: .*\) after 1 of 6 "
                                         r"steps: the weights written to .*w\.pt are those of step 1; the same command "
                                         r"with --resume continues to step 6"):
        meta = train(dataclasses.replace(TINY, max_minutes=0.0), tmp_path / "w.pt", tmp_path / "pairs", progress=False)
    assert meta["steps_done"] == 1


def test_a_meshes_file_that_is_not_a_mesh_is_refused_before_any_pair(tmp_path, capsys):
    """``--meshes garbage.stl``: the error came after every generated shape's training pair was made (about 20
    minutes at 64^3); now first, one line, exit 2, the cache untouched."""
    (tmp_path / "garbage.stl").write_bytes(bytes(range(256)) * 12)
    # trimesh reads it as an empty mesh, or (without its optional text decoder, as in CI) raises: both are named
    argv = ["--out", str(tmp_path / "w.pt"), "--cache", str(tmp_path / "pairs"), "--no-progress", "--n", "16",
            "--dips", "8", "--solver-iterations", "10", "--channels", "2", "--crop", "8", "--train-seeds", "5000",
            "5002", "--val-seeds", "5002", "5003", "--meshes", str(tmp_path / "garbage.stl")]
    with pytest.raises(SystemExit) as exit_:
        load_script("train_prior").main(argv)
    err = capsys.readouterr().err
    assert (exit_.value.code == 2
            and re.match(r"error: (cannot read )?mesh file .*garbage\.stl: corrupt, or not a mesh", err)), err
    assert not (tmp_path / "pairs").exists()


def test_resuming_on_pairs_made_by_other_first_stage_weights_says_so(tmp_path, shared_pairs):
    """A second stage resumed after its round's first-stage weights were retrained under the same name went on, exit
    0, on the inputs those new weights make (new cache files), its weights trained on both sets: now a warning
    names the change (digests recorded -> now); the same weights resume without a word."""
    first = tmp_path / "first.pt"
    save_weights(OccupancyDenoiser(TINY.channels), first, {"n": 16, "ndim": 3, "n_slabs_per_voxel": 1})
    config = dataclasses.replace(TINY, init_weights=str(first), steps=3,
                                 refine=load_script("train_prior").learned_round(weights=str(first)))
    cache, out = tmp_path / "pairs", tmp_path / "s2.pt"
    train(config, out, cache, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train(dataclasses.replace(config, steps=6), out, cache, resume=True, progress=False)
    retrained = OccupancyDenoiser(TINY.channels)
    torch.nn.init.constant_(retrained.out.bias, 0.01)
    save_weights(retrained, first, {"n": 16, "ndim": 3, "n_slabs_per_voxel": 1})
    with pytest.warns(UserWarning, match=r"checkpoint .*s2\.ckpt was trained on pairs made otherwise \(the second "
                                         r"stage's round weights \(--refine-weights; their bytes\) \w{12} -> \w{12} "
                                         r"\(recorded -> now\)\): the resumed run goes on"):
        assert train(dataclasses.replace(config, steps=9), out, cache, resume=True, progress=False)["steps_done"] == 9
