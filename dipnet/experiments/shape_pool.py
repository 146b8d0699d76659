"""The pool of shapes the random-case benchmarks dip: the 3D built-ins, the bundled meshes and the 2D built-ins.

Names as the benchmarks' rows show them: ``ball_3d``, ``box_3d``, ``torus_3d``, ``chamber_box_3d``, each bundled
mesh by its stem (``bunny``, ``hammer``, ...), ``disk_2d``, ``chamber_box_2d``, ``elephant_2d``.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dipnet.preprocessing.datasets import MESHES_DIR
from dipnet.shapes import builtin_shape, shape_from_file
from dipnet.shapes.base import Shape
from dipnet.experiments.bench_options import count_type, grid_size_type, refuse_bad_run_options, thread_count

BUILTINS = {2: ("disk", "chamber_box", "elephant"), 3: ("ball", "box", "torus", "chamber_box")}


def shape_makers() -> dict[str, tuple[int, Callable[[float], Shape]]]:
    """``name -> (ndim, make(radius in mm))`` of every shape in the pool (2D built-ins, 3D built-ins, meshes)."""
    makers: dict[str, tuple[int, Callable[[float], Shape]]] = {
        f"{name}_{ndim}d": (ndim, lambda r, name=name, ndim=ndim: builtin_shape(name, ndim, r))
        for ndim in (2, 3) for name in BUILTINS[ndim]}
    makers.update({path.stem: (3, lambda r, path=path: shape_from_file(str(path), 3, radius=r))
                   for path in sorted(MESHES_DIR.glob("*.ply"))})
    return makers


def shape_names(names: list[str] | None = None, ndim: int | None = None) -> list[str]:
    """The pool's names in its order: all (of dimension ``ndim``, if given), or ``names``.

    Raises:
        ValueError: naming every one of ``names`` the pool lacks (or of another dimension), and the known ones.
    """
    makers = {name: item for name, item in shape_makers().items() if ndim is None or item[0] == ndim}
    unknown = sorted(set(names or ()) - set(makers))
    if unknown:
        raise ValueError(f"--shapes: no shape named {', '.join(unknown)} (known: {', '.join(makers)})")
    return [name for name in makers if names is None or name in names]


def add_pool_options(parser: argparse.ArgumentParser, *, trials: int, resolution: int, shapes_help: str,
                     resolution_help: str = "voxels per axis of the grid",
                     json_help: str = "also write every row to this JSON file") -> None:
    """Add the options of a benchmark over random scans of the pool to ``parser``: ``--trials`` (scans per shape),
    ``--shapes``, ``--resolution`` (a default of 0: drawn per case, and 0 is allowed), ``--seed`` (2026), ``--threads``
    (2) and ``--json``."""
    parser.add_argument("--trials", type=count_type(1, "random scans per shape"), default=trials,
                        help="random scans per shape")
    parser.add_argument("--shapes", nargs="+", metavar="NAME", help=shapes_help)
    parser.add_argument("--resolution", type=grid_size_type(3, zero="drawn per case" if resolution == 0 else None),
                        default=resolution, help=resolution_help)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--threads", type=thread_count, default=2, help="torch threads")
    parser.add_argument("--json", type=Path, help=json_help)


def check_pool_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (``parser.error``: one line naming the option, exit 2) before any scan the options of
    :func:`add_pool_options` that no case could use: ``--seed`` below 0 and ``--json`` in a missing folder
    (:func:`~dipnet.experiments.bench_options.check_run_options`). ``--trials``, ``--resolution`` and ``--threads``
    are checked by their types."""
    refuse_bad_run_options(parser, args)


def start_pool_run(args: argparse.Namespace) -> np.random.Generator:
    """Set up a run of the options :func:`add_pool_options` added: torch's threads (``--threads``), dipnet's log
    quieted to errors (a benchmark's table is its output), and the random generator of its cases (``--seed``)."""
    torch.set_num_threads(args.threads)
    logging.getLogger("dipnet").setLevel(logging.ERROR)
    return np.random.default_rng(args.seed)
