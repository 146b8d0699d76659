"""Training pairs for the learned prior: (voxel reconstruction, true occupancy) of generated shapes
or of mesh files.

For each seed and each noise level, the procedural solid (:mod:`dipnet.shapes.procedural`), or a
mesh file turned by the seed's random rotation (:func:`rotated_mesh`), its farthest point at ``fill``
of the working ball, is dipped along ``dips`` Fibonacci directions (over the hemisphere, or with ``max_tilt_deg``
below 90 spread over the tilts a rig reaches, :func:`plan_directions`) by
the simulator with the benchmark's level sensor (:func:`dipnet.simulator.simulate.simulate_measurement`,
exact readings when noise-free, white noise at ``snr_db`` otherwise, both with ``quantum_mm=0``),
and the voxel solver (its defaults, so the data-chosen TV weight; ``solver_options`` override)
reconstructs the soft occupancy on the ``n^3`` grid. The target is the solid's partial-volume
occupancy (3^3 supersamples per voxel). The inputs are therefore what the solver really returns
on the benchmark's data, noise-free and noisy, not a cheaper stand-in.

The cache key of a pair holds its options and :func:`pairs_code` (the source digest of the shapes,
simulator, operators and solvers that made it), so a change to any of them (a new shape family that
redraws the seeds, a solver fix) makes the pairs afresh instead of reusing stale ones. A
second-stage pair's key also holds the digest of the learned-prior weights its round ran with
(:func:`refine_weights_digest`), so new first-stage weights under the same name make new inputs, and a
mesh pair's key the digest of the mesh file's bytes.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import warnings
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from dipnet.core.code_version import SIMULATION_PACKAGES, source_digest
from dipnet.core.grid import Grid
from dipnet.core.orientations import Reach, fibonacci_hemisphere
from dipnet.operators import make_operator
from dipnet.shapes.mesh import MeshShape, from_trimesh, load_mesh
from dipnet.shapes.procedural import generated_shape
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers.denoiser import existing_weights_path
from dipnet.solvers.voxel import VoxelSolver


def rotated_mesh(path: str | Path, seed: int, radius: float) -> MeshShape:
    """The mesh file ``path`` (:func:`~dipnet.shapes.mesh.load_mesh`: repaired and centred) turned by
    the uniformly random rotation of ``seed`` (``scipy.spatial.transform.Rotation.random``), scaled
    so that its farthest vertex is ``radius`` mm from the centre.

    Raises:
        ShapeError: the file is missing, unreadable or encloses no volume.
    """
    mesh = load_mesh(path).mesh.copy()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.random(random_state=int(seed)).as_matrix()
    mesh.apply_transform(turn)
    return from_trimesh(mesh, radius=radius, name=f"{Path(path).stem}-{seed}", source=str(path))


def plan_directions(dips: int, max_tilt_deg: float = 90.0) -> torch.Tensor:
    """The ``(dips, 3)`` directions of the pairs' plan: the Fibonacci hemisphere, or for ``max_tilt_deg`` below 90 the
    nearly uniform plan of a rig that tilts 0 to ``max_tilt_deg`` (:meth:`~dipnet.core.orientations.Reach.uniform`)."""
    if max_tilt_deg >= 90.0:
        return fibonacci_hemisphere(dips)
    return Reach(tilt_range_deg=(0.0, float(max_tilt_deg))).uniform(dips)


def _measurement(seed: int, n: int, dips: int, snr_db: float | None, fill: float, family: str | None = None,
                 mesh: str | None = None, max_tilt_deg: float = 90.0):
    """``(shape, measurement, operator)`` of one shape dipped ``dips`` times (see the module): the
    generated shape of ``seed`` and ``family`` (``None``: drawn by the seed,
    :func:`~dipnet.shapes.procedural.make_solid`), or the mesh file ``mesh`` turned by ``seed``'s rotation."""
    grid = Grid(n, 3)
    if mesh is not None:
        shape = rotated_mesh(mesh, seed, fill * grid.radius)
    else:
        shape = generated_shape(int(seed), family=family, radius=fill * grid.radius)
    sensor = LevelSensor(snr_db=snr_db, quantum_mm=0.0, seed=int(seed))
    _, measurement = simulate_measurement(shape, plan_directions(dips, max_tilt_deg), grid=grid, sensor=sensor,
                                          seed=int(seed), progress=False)
    return shape, measurement, make_operator(grid, measurement.directions, n)


def make_pair(seed: int, n: int = 64, dips: int = 41, snr_db: float | None = None, fill: float = 0.9,
              solver_options: Mapping | None = None, family: str | None = None, mesh: str | None = None,
              max_tilt_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray]:
    """``(reconstruction, truth)``, each ``(n, n, n)`` float32 in ``[0, 1]``, for one generated shape
    (of ``family``, or the seed's own when ``None``), or the mesh file ``mesh`` turned by the seed's
    rotation, dipped ``dips`` times (tilted at most ``max_tilt_deg``, :func:`plan_directions`), noise-free
    (``snr_db=None``) or with level-sensor noise at ``snr_db`` dB."""
    shape, measurement, operator = _measurement(seed, n, dips, snr_db, fill, family, mesh, max_tilt_deg)
    options = {"progress": False, "seed": int(seed), **dict(solver_options or {})}
    recon = VoxelSolver(**options).solve(measurement, operator)
    truth = shape.occupancy(operator.grid, supersample=3)
    return recon.occupancy.numpy().astype(np.float32), np.asarray(truth, dtype=np.float32)


def refine_input(seed: int, start: np.ndarray, refine: Mapping, n: int = 64, dips: int = 41,
                 snr_db: float | None = None, fill: float = 0.9, family: str | None = None,
                 mesh: str | None = None, max_tilt_deg: float = 90.0) -> np.ndarray:
    """A second-stage input ``(n, n, n)`` float32: :class:`VoxelSolver` with options ``refine`` (e.g.
    one round of ``solver=voxel_learned``) warm-started from ``start``, a pair's first-stage input,
    on the same measurement."""
    _, measurement, operator = _measurement(seed, n, dips, snr_db, fill, family, mesh, max_tilt_deg)
    options = {"progress": False, "seed": int(seed), **dict(refine), "warm_start": torch.from_numpy(start)}
    return VoxelSolver(**options).solve(measurement, operator).occupancy.numpy().astype(np.float32)


def pairs_key(seeds: Sequence[int], **options) -> str:
    """A short digest of what makes a set of pairs (seeds and options)."""
    text = json.dumps({"seeds": [int(s) for s in seeds], **options}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def pairs_code() -> str:
    """The code version of a pair: :func:`~dipnet.core.code_version.source_digest` of the packages
    that simulate the dips and of the operators and solvers that reconstruct them."""
    return source_digest(*SIMULATION_PACKAGES, "dipnet.operators", "dipnet.solvers")


def file_digest(path: str | Path) -> str:
    """The sha256 of a file's bytes, 12 hex characters (a cache key's or a record's short name for them)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


def refine_weights_digest(refine: Mapping) -> str | None:
    """The sha256 (12 hex characters) of the weights file of ``refine``'s learned prior (its
    ``priors.learned.weights``: a path, a shipped name, or ``None`` for the shipped first stage);
    ``None`` when ``refine`` has no learned prior.

    Raises:
        PriorWeightsError: the weights file is missing.
    """
    learned = (refine.get("priors") or {}).get("learned")
    if learned is None:
        return None
    return file_digest(existing_weights_path(learned.get("weights")))


def _make_and_save(file: Path, seed: int, snr_db: float | None, options: dict, refine: Mapping | None = None,
                   first: Path | None = None) -> None:
    """One pair, written to ``file``: made afresh, or with ``refine`` from the first-stage pair ``first``."""
    if refine is None:
        x, y = make_pair(seed, snr_db=snr_db, **options)
    else:
        with np.load(first) as saved:
            start, y = saved["input"], saved["target"]
        x = refine_input(seed, start, refine, options["n"], options["dips"], snr_db, options["fill"],
                         options.get("family"), options.get("mesh"), options.get("max_tilt_deg", 90.0))
    file.parent.mkdir(parents=True, exist_ok=True)
    part = file.with_name(f"{file.stem}.{os.getpid()}.part.npz")  # renamed whole: a kill leaves no cut-short pair
    np.savez_compressed(part, input=x, target=y)
    os.replace(part, file)


def _cached(file: Path, n: int) -> bool:
    """Whether ``file`` holds a whole cached pair (an input and a target of shape ``(n, n, n)``); a file that does
    not (cut short by a kill before pairs were written whole, damaged, or another program's) is named in a
    warning and made again."""
    if not file.is_file():
        return False
    try:
        with np.load(file) as saved:
            shapes = [saved[key].shape for key in ("input", "target")]
    except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file, the pair is made again
        problem = f"unreadable: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
    else:
        if shapes == [(n, n, n)] * 2:
            return True
        problem = f"its arrays have shapes {shapes[0]} and {shapes[1]}, not ({n}, {n}, {n})"
    warnings.warn(f"cached training pair {file} is not used ({problem}): it is made again", stacklevel=3)
    return False


def _make_missing(jobs: list[tuple], desc: str, total: int, progress: bool, workers: int) -> None:
    """Run :func:`_make_and_save` on ``jobs`` (its arguments) with ``workers`` processes."""
    with tqdm(total=total, initial=total - len(jobs), desc=desc, disable=not progress) as bar:
        if workers > 1 and len(jobs) > 1:
            context = multiprocessing.get_context("spawn")  # no fork of a process with torch threads
            with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=torch.set_num_threads,
                                     initargs=(1,)) as pool:
                for done in as_completed([pool.submit(_make_and_save, *job) for job in jobs]):
                    done.result()
                    bar.update()
        else:
            for job in jobs:
                _make_and_save(*job)
                bar.update()


def build_pairs(seeds: Sequence[int], cache: Path, n: int = 64, dips: int = 41,
                noise_levels: Sequence[float | None] = (None, 30.0), fill: float = 0.9,
                solver_options: Mapping | None = None, progress: bool = True, workers: int = 1,
                refine: Mapping | None = None, noisy_options: Mapping | None = None,
                family: str | None = None, mesh: str | Path | None = None, max_tilt_deg: float = 90.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """One pair per seed and noise level (``None`` = noise-free, else SNR in dB), stacked as
    ``(S * len(noise_levels), n, n, n)`` inputs and targets (seed-major). Each pair is cached as
    ``cache/pair_<seed>_<digest>.npz`` (written whole: a temporary file renamed into place), so an interrupted
    build resumes (a cached file that cannot be read is made again, with a warning); the missing pairs are made
    by ``workers`` processes (one per core: a pair costs 20-30 s of one core at 64^3, 41 dips).

    ``noisy_options`` are solver options for the noisy pairs only (e.g. ``{"noise_model": "correlated"}``,
    which acts only where the sensor's sigma is known); the noise-free pairs keep their digest.
    ``family`` makes every shape of that family (:data:`~dipnet.shapes.procedural.FAMILIES`) instead of
    the one its seed draws; it enters the digest only when given, so the seeds' own pairs keep theirs.
    ``mesh`` (a mesh file) makes each seed that mesh turned by the seed's random rotation
    (:func:`rotated_mesh`); its pairs are cached as ``cache/pair_<stem>-<seed>_<digest>.npz``, the digest
    holding the file's bytes. ``max_tilt_deg`` below 90 dips each shape along the plan of a rig that tilts
    that far at most (:func:`plan_directions`); it enters the digest only then.

    With ``refine`` (:class:`VoxelSolver` options) the pairs are second-stage ones: each first-stage
    input is refined by :func:`refine_input` (cached as ``cache/stage2_<seed>_<digest>.npz``, the
    digest holding ``refine`` and its learned weights' bytes too), the targets unchanged."""
    if family is not None and mesh is not None:
        raise ValueError("build_pairs takes a shape family or a mesh file, not both")
    code = pairs_code()
    digest = {} if mesh is None else {"mesh_bytes": file_digest(mesh)}
    name = "" if mesh is None else f"{Path(mesh).stem}-"

    def options_at(snr: float | None) -> dict:
        solver = {**dict(solver_options or {}), **(dict(noisy_options or {}) if snr is not None else {})}
        return {"n": n, "dips": dips, "fill": fill, "solver_options": solver, **({"family": family} if family else {}),
                **({"mesh": str(mesh)} if mesh is not None else {}),
                **({"max_tilt_deg": float(max_tilt_deg)} if max_tilt_deg < 90.0 else {})}

    def key(seed: int, snr: float | None, **more) -> str:
        options = {k: v for k, v in options_at(snr).items() if k != "mesh"}  # the file by its bytes, not its path
        return pairs_key([seed], snr_db=snr, **options, **digest, **more, code=code)

    files = {(int(seed), snr): Path(cache) / f"pair_{name}{seed}_{key(seed, snr)}.npz"
             for seed in seeds for snr in noise_levels}
    missing = [(file, seed, snr, options_at(snr)) for (seed, snr), file in files.items() if not _cached(file, n)]
    _make_missing(missing, "training pairs", len(files), progress, workers)
    if refine is not None:
        refine = dict(refine)
        firsts = files
        weights = refine_weights_digest(refine)
        files = {(seed, snr): Path(cache) / f"stage2_{name}{seed}_{key(seed, snr, refine=refine, weights=weights)}.npz"
                 for seed, snr in firsts}
        missing = [(file, seed, snr, options_at(snr), refine, firsts[seed, snr]) for (seed, snr), file in files.items()
                   if not _cached(file, n)]
        _make_missing(missing, "second-stage inputs", len(files), progress, workers)
    inputs, targets = [], []
    for file in files.values():
        with np.load(file) as saved:
            inputs.append(saved["input"])
            targets.append(saved["target"])
    return np.stack(inputs), np.stack(targets)
