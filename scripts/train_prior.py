"""Train the learned prior's 3D denoiser on generated shapes (CPU, deterministic by seed).

Builds (and caches) training pairs -- the voxel solver's reconstruction from ``--dips`` Fibonacci
dips of a generated shape, simulated as the quality benchmark does (noise-free, and with the level
sensor at ``--snr`` dB, for every seed), and the shape's partial-volume occupancy -- with
``--workers`` processes (about 30 minutes on 2 cores), then
trains :class:`dipnet.solvers.denoiser.OccupancyDenoiser` and writes the weights with their
config (``.pt`` + ``.json``). The bundled meshes are never used. A checkpoint (``.ckpt`` next to
the weights) is written every ``--checkpoint-every`` steps; ``--resume`` continues from it (also
to more ``--steps``), and ``--max-minutes`` stops a session early with a checkpoint.

    python scripts/train_prior.py                                   # the shipped weights' recipe
    python scripts/train_prior.py --out outputs/prior/denoiser64.pt --resume --steps 6000   # train longer
    python scripts/train_prior.py --steps 20 --train-seeds 1000 1004 --val-seeds 2000 2001  # a smoke run
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from dipnet.solvers.denoiser import SHIPPED_WEIGHTS
from dipnet.experiments.prior_training import TrainConfig, train


def parse_args(argv=None) -> argparse.Namespace:
    defaults = TrainConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("outputs/prior/denoiser64.pt"),
                   help=f"weights file (the shipped ones are {SHIPPED_WEIGHTS.name} in dipnet/data/priors)")
    p.add_argument("--cache", type=Path, default=Path("outputs/prior_pairs"), help="folder caching training pairs")
    p.add_argument("--train-seeds", type=int, nargs=2, default=list(defaults.train_seeds), metavar=("FIRST", "STOP"))
    p.add_argument("--val-seeds", type=int, nargs=2, default=list(defaults.val_seeds), metavar=("FIRST", "STOP"))
    for name in ("n", "dips", "solver_iterations", "channels", "steps", "batch", "crop", "seed",
                 "checkpoint_every"):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=getattr(defaults, name))
    for name in ("snr_db", "fill", "lr", "max_minutes"):
        p.add_argument("--" + name.replace("_", "-"), type=float, default=getattr(defaults, name))
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint next to --out")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the training")
    p.add_argument("--workers", type=int, default=2, help="processes making the missing training pairs")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {k: v for k, v in vars(args).items() if k in fields}
    config = TrainConfig(**{**values, "train_seeds": tuple(args.train_seeds), "val_seeds": tuple(args.val_seeds)})
    meta = train(config, args.out, args.cache, resume=args.resume, progress=not args.no_progress,
                 workers=args.workers)
    print(json.dumps({k: meta[k] for k in ("steps_done", "seconds", "validation")}))
    val = meta["validation"] or [0, float("nan"), float("nan")]
    print(f"RESULT steps={meta['steps_done']} seconds={meta['seconds']} val_mse={val[1]:.5f} input_mse={val[2]:.5f}")
    return meta


if __name__ == "__main__":
    main()
