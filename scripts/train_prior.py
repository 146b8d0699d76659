"""Train the learned prior's 3D denoiser on generated shapes (CPU, deterministic by seed).

Builds (and caches) training pairs -- the voxel solver's reconstruction from ``--dips`` Fibonacci
dips of a generated shape, simulated as the quality benchmark does (noise-free, and with the level
sensor at ``--snr`` dB, for every seed), and the shape's partial-volume occupancy -- with
``--workers`` processes (about 30 minutes on 2 cores), then
trains :class:`dipnet.solvers.denoiser.OccupancyDenoiser` and writes the weights with their
config (``.pt`` + ``.json``). The bundled meshes are never used. A checkpoint (``.ckpt`` next to
the weights) is written every ``--checkpoint-every`` steps; ``--resume`` continues from it (also
to more ``--steps``), and ``--max-minutes`` stops a session early with a checkpoint (the same run started
again without ``--resume`` is refused while that checkpoint is unfinished, rather than replacing it).

``--noise-model correlated`` solves the noisy pairs as ``solver=voxel_learned``'s voxel start does
(the slabs' errors as differences of cumulative readings; the shipped weights were trained with
``independent``, the default).

``--family-seeds FAMILY FIRST STOP`` adds training shapes of one named family (e.g. ``organic``, which
no seed draws by itself) to those of ``--train-seeds``; their pairs are cached under their own names.
``--meshes FILE ...`` adds mesh files (never the bundled test meshes), each turned by the random
rotations of ``--mesh-seeds FIRST STOP`` (default 0 4: four rotations, each noise-free and noisy).

``--stage 2`` makes the second stage (``later_priors`` of ``solver=voxel_learned``): each pair's input
goes through one round of ``solver=voxel_learned`` (its config, one round, the first-stage weights
``--refine-weights``, by default ``--init-weights``, the noise model ``--noise-model``, at the temperature
``--refine-temperature``: 0.25 and independent slabs made the shipped weights; the solver's refits now run at 0.125 with
correlated slabs, chosen afterwards on held-out shapes), about 25 more minutes on 2 cores, and the
first-stage weights are fine-tuned on those (``--init-weights denoiser64``, 2000 steps at lr 5e-4
unless given).

    python scripts/train_prior.py --seed 1                          # the shipped weights (the better of seeds 0 and 1)
    python scripts/train_prior.py --stage 2 --out outputs/prior/denoiser64_stage2.pt   # the shipped second stage
    python scripts/train_prior.py --out outputs/prior/denoiser64.pt --resume --steps 6000   # train longer
    python scripts/train_prior.py --family-seeds organic 3000 3032 --out outputs/prior/mixed.pt   # 64 + 32 shapes
    python scripts/train_prior.py --stage 2 --meshes more/*.obj --out outputs/prior/stage2_meshes.pt   # + real meshes
    python scripts/train_prior.py --steps 20 --train-seeds 1000 1004 --val-seeds 2000 2001  # a smoke run
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from omegaconf import OmegaConf

from dipnet.experiments.prior_training import STAGE2, TrainConfig, train
from dipnet.jobs.cli import user_errors
from dipnet.jobs.tuning import compose_job
from dipnet.jobs.warnings_once import log_warnings_once
from dipnet.shapes.procedural import FAMILIES
from dipnet.solvers.denoiser import SHIPPED_WEIGHTS


SHIPPED_REFINE_TEMPERATURE = 0.25
"""The fixed temperature of the round that made the shipped second stage's inputs."""


def learned_round(temperature: float = SHIPPED_REFINE_TEMPERATURE, noise_model: str = "independent",
                  weights: str | None = None) -> dict:
    """The options of one round of ``solver=voxel_learned`` with the first-stage weights (``weights``;
    ``None``: the shipped ``denoiser64``), no warm start (it starts from each pair's input), no threshold and no
    surface refit (the input is the occupancy), at the fixed sigmoid ``temperature``: the second stage's
    ``refine``. ``noise_model="independent"`` (with which the shipped second stage's inputs were made)
    drops the solver's noise model; ``"correlated"`` keeps it, as the solver's refits use it."""
    options = OmegaConf.to_container(compose_job(["solver=voxel_learned"]).solver, resolve=True)
    dropped = ("_target_", "warm_start", "later_priors", "progress", "seed", "threshold", "surface_refit")
    for key in dropped + (("noise_model", "white_share") if noise_model == "independent" else ()):
        options.pop(key, None)
    options["priors"]["learned"]["weights"] = weights  # one network, not the solver's candidates
    return {**options, "rounds": 1, "min_rounds": 1, "temperature_start": temperature, "temperature_end": temperature}


def parse_args(argv=None) -> argparse.Namespace:
    stage = argparse.ArgumentParser(add_help=False)
    stage.add_argument("--stage", type=int, choices=(1, 2), default=1,
                       help="1: train on voxel results; 2: fine-tune on their first learned round")
    known, _ = stage.parse_known_args(argv)
    defaults = TrainConfig(**(STAGE2 if known.stage == 2 else {}))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], parents=[stage])
    p.add_argument("--out", type=Path,
                   default=Path("outputs/prior") / f"denoiser64{'_stage2' if known.stage == 2 else ''}.pt",
                   help=f"weights file (the shipped ones are {SHIPPED_WEIGHTS.name} in dipnet/data/priors)")
    p.add_argument("--cache", type=Path, default=Path("outputs/prior_pairs"), help="folder caching training pairs")
    p.add_argument("--train-seeds", type=int, nargs=2, default=list(defaults.train_seeds), metavar=("FIRST", "STOP"))
    p.add_argument("--val-seeds", type=int, nargs=2, default=list(defaults.val_seeds), metavar=("FIRST", "STOP"))
    for name in ("n", "dips", "solver_iterations", "channels", "steps", "batch", "crop", "seed",
                 "checkpoint_every"):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=getattr(defaults, name))
    for name in ("snr_db", "fill", "lr", "max_minutes"):
        p.add_argument("--" + name.replace("_", "-"), type=float, default=getattr(defaults, name))
    p.add_argument("--max-tilt-deg", type=float, default=defaults.max_tilt_deg,
                   help="the pairs' dips tilted at most this far from the vertical (90: the whole hemisphere, the "
                        "shipped weights; e.g. 35 for a rig that tilts 0-35 deg, reach=authors_rig)")
    p.add_argument("--noise-model", choices=("independent", "correlated"), default=defaults.noise_model,
                   help="the noise model of the noisy pairs' voxel solve and of stage 2's round "
                        "(correlated: as solver=voxel_learned uses it)")
    p.add_argument("--refine-temperature", type=float, default=None,
                   help="stage 2: the sigmoid temperature of the round that makes the inputs "
                        f"(default {SHIPPED_REFINE_TEMPERATURE}, which made the shipped weights)")
    p.add_argument("--family-seeds", nargs=3, action="append", default=[], metavar=("FAMILY", "FIRST", "STOP"),
                   help="more training shapes of one named family (repeatable), e.g. organic 3000 3032")
    p.add_argument("--meshes", type=Path, nargs="+", default=[], metavar="FILE",
                   help="more training shapes from mesh files, each under the rotations of --mesh-seeds")
    p.add_argument("--mesh-seeds", type=int, nargs=2, default=None, metavar=("FIRST", "STOP"),
                   help=f"the random rotations of each of --meshes (default {' '.join(map(str, defaults.mesh_seeds))})")
    p.add_argument("--init-weights", default=defaults.init_weights,
                   help="weights to start from (file or shipped name); default: a new network (stage 1)")
    p.add_argument("--refine-weights", default=None,
                   help="stage 2: the first-stage weights of the round that makes the inputs (default: --init-weights; "
                        "set it to fine-tune the second stage itself, e.g. --init-weights denoiser64_stage2 "
                        "--refine-weights denoiser64)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint next to --out")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the training")
    p.add_argument("--workers", type=int, default=2, help="processes making the missing training pairs")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def refine_of(args: argparse.Namespace) -> dict | None:
    """Stage 2: the round that makes the inputs (with the first-stage weights trained on, the noise
    model of the noisy pairs); stage 1: ``None``."""
    if args.stage != 2:
        return None
    first = args.refine_weights or args.init_weights
    weights = None if first == STAGE2["init_weights"] else str(first)
    temperature = SHIPPED_REFINE_TEMPERATURE if args.refine_temperature is None else args.refine_temperature
    return learned_round(temperature, args.noise_model, weights)


def check_ignored(args: argparse.Namespace) -> None:
    """Raise ``ValueError`` for an option given that this command would ignore: stage 2's ``--refine-temperature``
    or ``--refine-weights`` at stage 1 (its pairs are voxel results, made without a learned round: the weights
    written would be a first stage's), or ``--mesh-seeds`` without ``--meshes`` (rotations of no mesh)."""
    if args.stage != 2:
        given = [f"--{name.replace('_', '-')}" for name in ("refine_temperature", "refine_weights")
                 if getattr(args, name) is not None]
        if given:
            raise ValueError(f"{' and '.join(given)} set the second stage's round, which stage 1 does not run (its "
                             "inputs are voxel results): add --stage 2 to train the second stage, or remove them")
    if args.mesh_seeds is not None and not args.meshes:
        raise ValueError(f"--mesh-seeds {args.mesh_seeds[0]} {args.mesh_seeds[1]} sets the rotations of each of "
                         "--meshes, and no --meshes are given: add --meshes FILE ..., or remove --mesh-seeds")


def config_of(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of the parsed command line."""
    check_ignored(args)
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {k: v for k, v in vars(args).items() if k in fields}
    mesh_seeds = TrainConfig.mesh_seeds if args.mesh_seeds is None else tuple(args.mesh_seeds)
    return TrainConfig(**{**values, "train_seeds": tuple(args.train_seeds), "val_seeds": tuple(args.val_seeds),
                          "refine": refine_of(args), "family_seeds": family_seeds(args.family_seeds),
                          "meshes": mesh_files(args.meshes, mesh_seeds), "mesh_seeds": mesh_seeds})


def mesh_files(paths: list[Path], seeds: list[int]) -> tuple[str, ...]:
    """``--meshes`` as strings, checked: each an existing file, none repeated, and ``--mesh-seeds``
    FIRST < STOP when there are any.

    Raises:
        ValueError: a missing or repeated file, or an empty rotation range.
    """
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise ValueError(f"--meshes: no such file: {', '.join(missing)}")
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError("--meshes: a file is named twice")
    if paths and seeds[1] <= seeds[0]:
        raise ValueError(f"--mesh-seeds {seeds[0]} {seeds[1]}: FIRST must be below STOP")
    return tuple(str(p) for p in paths)


def family_seeds(specs: list[list[str]]) -> dict[str, tuple[int, int]]:
    """``{family: (first, stop)}`` of ``--family-seeds`` entries ``FAMILY FIRST STOP``.

    Raises:
        ValueError: an unknown family, a repeated one, or an empty or unreadable seed range.
    """
    out: dict[str, tuple[int, int]] = {}
    for family, first, stop in specs:
        if family not in FAMILIES or family in out:
            raise ValueError(f"--family-seeds: {family!r} is unknown or repeated; families: {', '.join(FAMILIES)}")
        try:
            seeds = (int(first), int(stop))
        except ValueError:
            seeds = (0, 0)
        if seeds[1] <= seeds[0]:
            raise ValueError(f"--family-seeds {family} {first} {stop}: FIRST and STOP must be whole numbers, "
                             "FIRST < STOP")
        out[family] = seeds
    return out


def main(argv=None) -> dict:
    """Train as the command line says; a bad option or weights file: one line ``error: ...`` and exit 2."""
    args = parse_args(argv)
    log_warnings_once()  # a warning (a checkpoint not used) in one line, without the source line
    with user_errors():
        if args.threads < 1 or args.workers < 1:
            raise ValueError(f"--threads and --workers must be positive integers, "
                             f"got {args.threads} and {args.workers}")
        torch.set_num_threads(args.threads)
        config = config_of(args)
        meta = train(config, args.out, args.cache, resume=args.resume, progress=not args.no_progress,
                     workers=args.workers)
    print(json.dumps({k: meta[k] for k in ("steps_done", "seconds", "validation")}))
    val = meta["validation"] or [0, float("nan"), float("nan")]
    print(f"RESULT steps={meta['steps_done']} seconds={meta['seconds']} val_mse={val[1]:.5f} input_mse={val[2]:.5f}")
    return meta


if __name__ == "__main__":
    main()
