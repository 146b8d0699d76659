"""Training the learned prior's denoiser on generated shapes (``scripts/train_prior.py``).

Pairs (:mod:`dipnet.experiments.prior_pairs`) of voxel reconstructions from few dips and the true occupancy
of generated shapes (never the bundled meshes) train :class:`~dipnet.solvers.denoiser.OccupancyDenoiser`
by Adam on the mean squared error over random ``crop^3`` blocks, with random flips and axis
permutations (the dip directions cover the sphere evenly, so the artifacts have no preferred axis).
Every random draw comes from one generator seeded by ``seed``; its state is saved in each
checkpoint, so a run resumed with ``resume=True`` continues the same sequence of batches.

A second stage (``init_weights`` and ``refine`` set) fine-tunes trained weights on second-stage
pairs: the first-stage inputs after one round of the learned prior (``refine``, the options of that
round), so the network learns the artifacts the later plug-and-play rounds meet
(``solver=voxel_learned``'s ``later_priors``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from dipnet.solvers.checkpoint import read_state, write_state
from dipnet.solvers.denoiser import OccupancyDenoiser, load_weights, save_weights
from dipnet.experiments.prior_pairs import build_pairs, file_digest, pairs_code, refine_weights_digest
from dipnet.shapes.mesh import load_mesh
from dipnet.simulator.physics import check_snr_db
from dipnet.solvers.voxel import VoxelSolver


@dataclass
class TrainConfig:
    """What a training run does (stored in the weights' meta).

    Attributes:
        train_seeds: ``[first, stop)`` of the generated shapes trained on.
        val_seeds: ``[first, stop)`` of the held-out generated shapes for the validation loss.
        n, dips, snr_db, fill: the pairs' grid, number of Fibonacci dips, the level-sensor SNR (dB)
            of the noisy pair of each seed (each seed also gives a noise-free pair), and the
            shapes' size (farthest point / working-ball radius).
        max_tilt_deg: the largest tilt of the pairs' dips from the vertical (degrees; 90: the whole hemisphere, as
            the shipped weights; less: the plan of a rig that tilts that far,
            :func:`~dipnet.experiments.prior_pairs.plan_directions`).
        solver_iterations: voxel-solver steps of the reconstructions (400: the solver's default).
        noise_model: the voxel solver's noise model for the noisy pairs (``"correlated"``: as the start
            of ``solver=voxel_learned`` with the sensor's sigma; noise-free pairs are the same either way).
        channels, steps, batch, crop, lr: network width, Adam steps, blocks per step, block side
            (voxels), learning rate (cosine decay to 5%).
        seed: the run's random seed.
        checkpoint_every: steps between checkpoints.
        max_minutes: the session's minutes of training: the first step past them stops it, with a checkpoint;
            resume continues.
        init_weights: weights to start from (a file or shipped name, see
            :func:`~dipnet.solvers.denoiser.weights_path`); ``None``: a new network (its output the input).
        refine: :class:`~dipnet.solvers.voxel.VoxelSolver` options that turn each pair's input into a
            second-stage one (:func:`~dipnet.experiments.prior_pairs.build_pairs`); ``None``: first stage.
        family_seeds: more training shapes, each of one named family
            (:data:`~dipnet.shapes.procedural.FAMILIES`): ``{family: [first, stop)}``, e.g.
            ``{"organic": (3000, 3032)}`` (the family only made when named); empty: the ``train_seeds``
            alone, each of the family its seed draws.
        meshes: more training shapes from mesh files (paths), each turned by the random rotations of
            ``mesh_seeds`` (:func:`~dipnet.experiments.prior_pairs.rotated_mesh`); empty: none.
        mesh_seeds: ``[first, stop)`` of the rotations of each of ``meshes``.
    """

    train_seeds: tuple[int, int] = (1000, 1064)
    val_seeds: tuple[int, int] = (2000, 2008)
    n: int = 64
    dips: int = 41
    snr_db: float = 30.0
    fill: float = 0.9
    max_tilt_deg: float = 90.0
    solver_iterations: int = 400
    noise_model: str = "independent"
    channels: int = 16
    steps: int = 3500
    batch: int = 4
    crop: int = 32
    lr: float = 1e-3
    seed: int = 0
    checkpoint_every: int = 250
    max_minutes: float = 90.0
    init_weights: str | None = None
    refine: dict | None = None
    family_seeds: dict = field(default_factory=dict)
    meshes: tuple[str, ...] = ()
    mesh_seeds: tuple[int, int] = (0, 4)
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Raise :class:`TrainConfigError` for an option out of range, before any pair is made."""
        _seed_range("train_seeds", self.train_seeds)
        _seed_range("val_seeds", self.val_seeds)
        (a, b), (c, d) = self.train_seeds, self.val_seeds
        if max(a, c) < min(b, d):
            raise TrainConfigError(f"val_seeds {c} {d} share the seeds {max(a, c)}..{min(b, d) - 1} with train_seeds "
                                   f"{a} {b}: the validation loss would score shapes trained on, not held-out ones; "
                                   "give seed ranges that do not overlap")
        for family, seeds in self.family_seeds.items():
            _seed_range(f"family_seeds {family}", seeds)
        if self.meshes:
            _seed_range("mesh_seeds", self.mesh_seeds)
        for name in ("dips", "solver_iterations", "channels", "steps", "batch", "checkpoint_every"):
            _whole(name, getattr(self, name), 1)
        _whole("seed", self.seed, 0)
        _whole("n", self.n, 4)
        _whole("crop", self.crop, 4)
        if self.n % 4 or self.crop % 4 or self.crop > self.n:
            raise TrainConfigError(f"n and crop must be multiples of 4 (the denoiser halves the grid twice) with "
                                   f"crop <= n (voxels), got n={self.n}, crop={self.crop}")
        try:
            check_snr_db(self.snr_db)
        except ValueError as exc:
            raise TrainConfigError(str(exc)) from None
        if not 0 < self.max_tilt_deg <= 90:
            raise TrainConfigError(f"max_tilt_deg must be a tilt in (0, 90] degrees, got {self.max_tilt_deg!r}")
        if not 0 < self.fill <= 1:
            raise TrainConfigError(f"fill must be a number in (0, 1], got {self.fill!r}")
        if not 0 < self.lr < math.inf:
            raise TrainConfigError(f"lr must be a positive, finite learning rate, got {self.lr!r}")
        if not self.max_minutes >= 0:
            raise TrainConfigError(f"max_minutes must be a number >= 0 (0: stop after the first step; inf: no "
                                   f"limit), got {self.max_minutes!r}")
        if self.noise_model not in NOISE_MODELS:
            raise TrainConfigError(f"noise_model must be one of {', '.join(NOISE_MODELS)}, got {self.noise_model!r}")


#: The voxel solver's noise models of the noisy pairs (:attr:`TrainConfig.noise_model`).
NOISE_MODELS = ("independent", "correlated")


class TrainConfigError(ValueError):
    """A training option is out of range (:class:`TrainConfig`), the weights to start from do not fit, or
    the training diverged (a learning rate too large)."""


def _seed_range(name: str, seeds) -> None:
    """Raise :class:`TrainConfigError` unless ``seeds`` is ``(first, stop)``, whole numbers, ``0 <= first < stop``
    (a negative seed seeds no random generator: it failed after the training pairs were made)."""
    if (len(seeds) != 2 or any(isinstance(s, bool) or not isinstance(s, int) for s in seeds)
            or not 0 <= seeds[0] < seeds[1]):
        raise TrainConfigError(f"{name} must be FIRST STOP, whole numbers with 0 <= FIRST < STOP (the seeds "
                               f"FIRST..STOP-1), got {' '.join(map(str, seeds))}")


def _whole(name: str, value, low: int) -> None:
    """Raise :class:`TrainConfigError` unless ``value`` is an integer >= ``low``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise TrainConfigError(f"{name} must be {'a positive integer' if low == 1 else f'an integer >= {low}'}, "
                               f"got {value!r}")


#: What ``--stage 2`` changes (the shipped ``denoiser64_stage2``): fine-tune the first stage, gently.
STAGE2 = {"init_weights": "denoiser64", "steps": 2000, "lr": 5e-4}


def _pairs(config: TrainConfig, seeds: tuple[int, int], cache: Path, progress: bool, workers: int,
           family: str | None = None, mesh: str | None = None):
    return build_pairs(range(*seeds), cache=cache, n=config.n, dips=config.dips, noise_levels=(None, config.snr_db),
                       fill=config.fill, solver_options={"iterations": config.solver_iterations}, progress=progress,
                       workers=workers, refine=config.refine,
                       noisy_options={} if config.noise_model == "independent" else {"noise_model": config.noise_model},
                       family=family, mesh=mesh, max_tilt_deg=config.max_tilt_deg)


def training_pairs(config: TrainConfig, cache: Path, progress: bool = True, workers: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The training pairs of ``config``: those of ``train_seeds``, then those of each of ``family_seeds``,
    then those of each of ``meshes`` (stacked as :func:`~dipnet.experiments.prior_pairs.build_pairs` stacks them)."""
    parts = [_pairs(config, config.train_seeds, cache, progress, workers)]
    parts += [_pairs(config, tuple(seeds), cache, progress, workers, family)
              for family, seeds in sorted(config.family_seeds.items())]
    parts += [_pairs(config, tuple(config.mesh_seeds), cache, progress, workers, mesh=mesh) for mesh in config.meshes]
    return np.concatenate([x for x, _ in parts]), np.concatenate([y for _, y in parts])


def mesh_note(config: TrainConfig) -> str:
    """What ``config.meshes`` adds to the weights' ``trained_on``: each file's name and the sha256 of its
    bytes (12 hex characters), and the rotations; empty without meshes."""
    if not config.meshes:
        return ""
    files = ", ".join(f"{Path(m).name} ({file_digest(m)})" for m in config.meshes)
    first, stop = config.mesh_seeds
    return f"; mesh files {files}, each under the random rotations of seeds {first}..{stop - 1}"


def random_batch(inputs: torch.Tensor, targets: torch.Tensor, batch: int, crop: int, generator: torch.Generator
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """``batch`` random ``crop^3`` blocks ``(B, 1, c, c, c)`` of random pairs, each flipped along
    random axes and with its axes permuted at random (the same for input and target)."""
    n = inputs.shape[-1]
    xs, ys = [], []
    for _ in range(batch):
        i = int(torch.randint(inputs.shape[0], (1,), generator=generator))
        z, y, x = (int(v) for v in torch.randint(n - crop + 1, (3,), generator=generator))
        block = torch.stack([inputs[i], targets[i]])[:, z:z + crop, y:y + crop, x:x + crop]
        flips = [d + 1 for d in range(3) if bool(torch.rand(1, generator=generator) < 0.5)]
        block = block.flip(flips) if flips else block
        block = block.permute(0, *(int(a) + 1 for a in torch.randperm(3, generator=generator)))
        xs.append(block[0])
        ys.append(block[1])
    return torch.stack(xs)[:, None], torch.stack(ys)[:, None]


def validation_loss(model: OccupancyDenoiser, inputs: torch.Tensor, targets: torch.Tensor) -> tuple[float, float]:
    """``(MSE of the denoised volumes, MSE of the inputs)`` over whole held-out volumes."""
    with torch.no_grad():
        out = torch.cat([model(inputs[i:i + 1, None]) for i in range(inputs.shape[0])])[:, 0]
    return float(F.mse_loss(out, targets)), float(F.mse_loss(inputs, targets))


def check_diverged(what: str, value: float, step: int, config: TrainConfig, largest: float = math.inf) -> None:
    """Raise :class:`TrainConfigError` when ``value`` (the ``what`` loss at ``step``, a mean squared error of
    occupancies) is NaN, infinite or above ``largest``: the training diverged, and nothing of it may be saved."""
    if not (math.isfinite(value) and value <= largest):
        raise TrainConfigError(f"training diverged: the {what} loss became {value:.3g} at step {step} of "
                               f"{config.steps} (lr {config.lr:g}); no weights or checkpoint written: try a lower --lr")


def same_run(saved: dict, config: TrainConfig) -> bool:
    """Whether a checkpoint's config ``saved`` is ``config``'s run, up to ``steps`` and ``max_minutes``
    (a resumed run may go on longer). A field ``saved`` lacks (a checkpoint older than the field)
    takes its default, the behaviour before the field existed."""
    old = dataclasses.asdict(TrainConfig()) | saved
    return old | {"steps": config.steps, "max_minutes": config.max_minutes} == dataclasses.asdict(config)


#: The fields of a training checkpoint (``<out>.ckpt``).
CHECKPOINT_FIELDS = frozenset({"config", "model", "optimizer", "scheduler", "generator", "step", "history", "seconds",
                               "pairs"})


def pairs_made_by(config: TrainConfig) -> dict[str, str | None]:
    """What makes ``config``'s pairs beyond its options (recorded in each checkpoint as ``pairs``): the code version
    (:func:`~dipnet.experiments.prior_pairs.pairs_code`), the digest of the second stage's round weights (their
    bytes: retrained first-stage weights under the same name make other inputs) and of each of ``meshes``."""
    return {"code": pairs_code(),
            "refine_weights": None if config.refine is None else refine_weights_digest(config.refine),
            "meshes": " ".join(file_digest(mesh) for mesh in config.meshes)}


def resumable_checkpoint(path: Path, config: TrainConfig) -> dict | None:
    """The training checkpoint at ``path`` that ``config``'s run continues from, or ``None`` (with a warning naming
    the file) when there is none, or it cannot be read or is not a training checkpoint (truncated, empty, another
    file): the training then starts at step 0 and its first checkpoint replaces the file.

    Raises:
        TrainConfigError: the checkpoint is another run's (:func:`same_run`), naming the options that differ:
            resuming it would continue that run under this one's name, starting afresh would overwrite it.
    """
    if not path.is_file():
        _warn(f"--resume: there is no checkpoint {path} (none written yet, or another --out?); training from step 0")
        return None
    saved, problem = read_state(path)
    if problem is None and not (isinstance(saved, dict) and set(saved) | {"pairs"} == CHECKPOINT_FIELDS
                                and isinstance(saved["config"], dict)):  # pairs: absent from older checkpoints
        problem = "it is not a training checkpoint of scripts/train_prior.py"
    if problem is not None:
        _warn(f"checkpoint {path} is not used: {problem}; training from step 0")
        return None
    if not same_run(saved["config"], config):
        recorded = dataclasses.asdict(TrainConfig()) | saved["config"]
        now = dataclasses.asdict(config) | {"steps": recorded["steps"], "max_minutes": recorded["max_minutes"]}
        differ = "; ".join(f"{key} {recorded.get(key)!r} -> {now.get(key)!r}"
                           for key in sorted(set(recorded) | set(now))
                           if _plain(recorded.get(key)) != _plain(now.get(key)))
        raise TrainConfigError(f"checkpoint {path} was made with other options ({differ} (recorded -> now)): give "
                               "the same options to resume it, or another --out to train afresh")
    recorded, now = saved.get("pairs") or {}, pairs_made_by(config)
    labels = {"code": "the code version of the simulation, operators and solvers",
              "refine_weights": "the second stage's round weights (--refine-weights; their bytes)",
              "meshes": "the bytes of --meshes"}
    changed = [f"{label} {recorded[key]} -> {now[key]}" for key, label in labels.items()
               if key in recorded and recorded[key] != now[key]]
    if changed:
        _warn(f"checkpoint {path} was trained on pairs made otherwise ({'; '.join(changed)} (recorded -> now)): the "
              "resumed run goes on with the pairs made now, so its weights are trained on both; start afresh "
              "(another --out) for weights of the new pairs alone")
    return saved


def refuse_unfinished(path: Path, config: TrainConfig) -> None:
    """Raise :class:`TrainConfigError` when ``path`` holds an unfinished checkpoint of ``config``'s own run (stopped
    by ``max_minutes`` or killed): training afresh without ``resume`` would replace it at its first checkpoint and
    lose the steps it holds. A missing, damaged or other run's checkpoint is left to be replaced."""
    if not path.is_file():
        return
    saved, problem = read_state(path)
    if problem is not None or not isinstance(saved, dict) or not isinstance(saved.get("config"), dict):
        return
    step, steps = saved.get("step"), saved["config"].get("steps")
    if same_run(saved["config"], config) and isinstance(step, int) and isinstance(steps, int) and step < steps:
        raise TrainConfigError(f"checkpoint {path} holds this run stopped at step {step} of {steps}: training afresh "
                               "would replace it and lose those steps; add --resume to continue it, or delete it or "
                               "give another --out to start again")


def _plain(value):
    """``value`` with tuples as lists (as a checkpoint's config holds them)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _warn(message: str) -> None:
    warnings.warn(message, stacklevel=3)


def _initial_model(config: TrainConfig) -> OccupancyDenoiser:
    """A new network of ``config.channels``, or the weights ``config.init_weights`` (same width)."""
    if config.init_weights is None:
        return OccupancyDenoiser(config.channels)
    model, meta = load_weights(config.init_weights)
    if int(meta["channels"]) != config.channels or int(meta["n"]) != config.n:
        raise TrainConfigError(f"init_weights {config.init_weights!r} have {meta['channels']} channels "
                               f"for a {meta['n']}^3 grid, the config {config.channels} channels and n={config.n}")
    return model


def _check_refine(config: TrainConfig) -> None:
    """Raise :class:`~dipnet.solvers.denoiser.PriorWeightsError` (missing, unreadable) or :class:`TrainConfigError`
    (another grid, or options its :class:`~dipnet.solvers.voxel.VoxelSolver` refuses, e.g. ``--refine-temperature
    0``) for ``config.refine``'s learned round (its weights: ``--refine-weights``), which the second stage first
    runs after every first-stage pair is made."""
    if config.refine is None:
        return
    learned = (config.refine.get("priors") or {}).get("learned")
    if learned is not None:
        weights = learned.get("weights")
        _, meta = load_weights(weights)
        if int(meta["n"]) != config.n:
            raise TrainConfigError(f"the second stage's round runs on the pairs' {config.n}^3 grid, but its weights "
                                   f"{weights or 'denoiser64'!s} (--refine-weights, or --init-weights) were trained "
                                   f"for {meta['n']}^3: give first-stage weights of n={config.n}")
    try:
        VoxelSolver(**{"progress": False, **config.refine})
    except (TypeError, ValueError) as exc:
        raise TrainConfigError(f"the second stage's round (at --refine-temperature "
                               f"{config.refine.get('temperature_start')!r}) cannot run: {exc}") from None


def train(config: TrainConfig, out: Path, cache: Path, resume: bool = False, progress: bool = True,
          workers: int = 1) -> dict:
    """Train (or continue) and write the weights to ``out`` (``.pt`` + ``.json``); the checkpoint
    is ``out.with_suffix(".ckpt")``; missing training pairs are made by ``workers`` processes.
    Returns the weights' meta (losses, steps, seconds).

    With ``resume`` the run continues from the checkpoint (:func:`resumable_checkpoint`: none, or one that cannot
    be read, starts at step 0 with a warning). Checkpoints are written atomically
    (:func:`~dipnet.solvers.checkpoint.write_state`): a run killed mid-write leaves the previous one whole.

    Raises:
        TrainConfigError: a bad option, starting weights or second-stage round weights, an ``out`` that is a
            folder, a checkpoint of another run to resume (these, and a file of ``meshes`` that is not a mesh
            (``ShapeError``), before any pair is made), or a loss that became NaN or infinite, or a validation
            loss above 1 (before any weights or checkpoint of the diverged network are written).
    """
    if config.init_weights is not None:
        _initial_model(config)  # weights that are missing, damaged or of another size: an error before the pairs
    _check_refine(config)  # the second stage's round's too
    for mesh in config.meshes:  # a file that is not a mesh: an error now, not after the generated shapes' pairs
        load_mesh(mesh)
    out = Path(out)
    if out.is_dir():  # now, not by a traceback when the trained weights are written
        raise TrainConfigError(f"the weights file {out} is a folder: give a file, e.g. {out / 'denoiser64.pt'}")
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt_path = out.with_suffix(".ckpt")
    saved = resumable_checkpoint(ckpt_path, config) if resume else None  # another run's: refused before the pairs
    if not resume:
        refuse_unfinished(ckpt_path, config)
    made_by = pairs_made_by(config)
    x_np, y_np = training_pairs(config, cache, progress, workers)
    xv_np, yv_np = _pairs(config, config.val_seeds, cache, progress, workers)
    inputs, targets = torch.from_numpy(x_np), torch.from_numpy(y_np)
    val_in, val_target = torch.from_numpy(xv_np), torch.from_numpy(yv_np)
    torch.manual_seed(config.seed)
    model = _initial_model(config)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(i / config.steps, 1.0))))
    generator = torch.Generator().manual_seed(config.seed)
    step, history, seconds = 0, {"train": [], "val": []}, 0.0
    if saved is not None:
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["optimizer"])
        sched.load_state_dict(saved["scheduler"])
        generator.set_state(saved["generator"])
        step, history, seconds = saved["step"], saved["history"], saved["seconds"]

    def checkpoint() -> None:
        write_state({"config": dataclasses.asdict(config), "model": model.state_dict(), "optimizer": opt.state_dict(),
                     "scheduler": sched.state_dict(), "generator": generator.get_state(), "step": step,
                     "history": history, "seconds": seconds, "pairs": made_by}, ckpt_path)

    started = time.perf_counter() - seconds
    session_start = time.perf_counter()
    model.train()
    with tqdm(total=config.steps, initial=step, desc="train prior", disable=not progress) as bar:
        while step < config.steps:
            x, y = random_batch(inputs, targets, config.batch, config.crop, generator)
            opt.zero_grad(set_to_none=True)
            loss = F.mse_loss(model(x), y)
            value = loss.item()
            check_diverged("training", value, step + 1, config)
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            history["train"].append(value)
            bar.update()
            due = step % config.checkpoint_every == 0 or step == config.steps
            over = (time.perf_counter() - session_start) / 60 > config.max_minutes
            if due:
                model.eval()
                val, baseline = validation_loss(model, val_in, val_target)
                check_diverged("validation", val, step, config, largest=1.0)  # worse than any volume in [0, 1]
                model.train()
                history["val"].append([step, val, baseline])
                bar.set_postfix(train=f"{np.mean(history['train'][-50:]):.4f}", val=f"{val:.4f}",
                                input=f"{baseline:.4f}", refresh=False)
            if due or over:  # out of time: a checkpoint here, so that --resume loses no step
                seconds = time.perf_counter() - started
                checkpoint()
            if over:
                break
    seconds = time.perf_counter() - started
    if step < config.steps:  # weights written like a finished run's: say they are not
        _warn(f"training stopped by max_minutes={config.max_minutes:g} (--max-minutes: the session's minutes of "
              f"training) after {step} of {config.steps} steps: the weights written to {out} are those of step "
              f"{step}; the same command with --resume continues to step {config.steps}")
    meta = {"n": config.n, "ndim": 3, "n_slabs_per_voxel": 1, "config": dataclasses.asdict(config),
            "steps_done": step, "seconds": round(seconds, 1),
            "validation": history["val"][-1] if history["val"] else None,
            "trained_on": "generated shapes (dipnet.shapes.procedural), seeds "
                          f"{config.train_seeds[0]}..{config.train_seeds[1] - 1}"
            + "".join(f", {family} seeds {a}..{b - 1}" for family, (a, b) in sorted(config.family_seeds.items()))
            + mesh_note(config)
            + ("" if config.refine is None else ", inputs after one round of the learned prior (second stage)")}
    model.eval()
    save_weights(model, out, meta)
    return meta
