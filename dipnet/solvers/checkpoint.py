"""Checkpoints of a long optimisation, so that an interrupted solve continues where it stopped.

:class:`Checkpoint` is handed to a solver (``OptimisationSolver(checkpoint=...)``); the
optimisation loop (:func:`dipnet.solvers.optimize.optimise`) calls :meth:`Checkpoint.restore`
before its first step and :meth:`Checkpoint.save` after every step. Every ``every`` steps, and
when a stage ends, it writes the parameters, the optimiser's and scheduler's state, the loss
history and the lagged state of the stage's priors (a ``red`` mode learned prior's reused denoiser output and call
count, :meth:`~dipnet.solvers.learned.LearnedPrior.lag_state`) to ``<directory>/<stage>.pt``. A finished stage
is marked done, so a resumed multi-stage solve (coarse then fine) skips it. A job holds its checkpoint directory
while it solves (:func:`dipnet.core.locks.checkpoint_directory_lock`), so two jobs never write into one at once.

Writing is atomic: a temporary file, flushed to disk (``fsync``), then renamed over the old
one, so a kill mid-write leaves the previous checkpoint intact. A write that fails (a full
disk) removes its temporary file and warns; the solve goes on without that checkpoint.

Reading never runs code from the file (``torch.load(..., weights_only=True)``: tensors, numbers,
strings, lists and dicts only) and checks what it read: the record's keys, the parameters'
shapes and dtypes, the step count, and the problem it was made for (the fingerprint: step count,
optimiser, parameter shapes, measured data, grid and operator, the bytes of the learned prior's weights, and the
solver's options, :func:`solver_settings`). A checkpoint that cannot be read (truncated, empty, foreign bytes) or
does not fit is ignored with one warning naming the file (and the options that differ, when
those are what differs), and that stage starts afresh: a damaged checkpoint never blocks a rerun.

Adam and the schedules are deterministic, so a resumed solve gives the same result as an
uninterrupted one (to rounding). A checkpoint written before the lagged state was recorded (no ``lagged`` field,
:data:`LEGACY_FIELDS`) is still resumed as before: exactly for every prior without such state (``anchor`` mode, the
shipped recipe), while a ``red`` mode learned prior starts its lag afresh (D evaluated at the first resumed step), so
that solve ends near, not bit-identical to, an uninterrupted one (logged).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import pickle
import re
import warnings
from collections.abc import Mapping, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

import torch

from dipnet.core.atomic_write import write_atomically
from dipnet.core.warn import log_and_warn
from dipnet.solvers.base import Solver

log = logging.getLogger(__name__)

#: The fields of a checkpoint record.
FIELDS = frozenset({"fingerprint", "step", "done", "params", "optimizer", "scheduler", "history", "lagged"})
#: The fields of a record written before the priors' lagged state was saved (resumed without it; module docstring).
LEGACY_FIELDS = FIELDS - {"lagged"}
#: Solver attributes that do not change the optimisation, so :func:`solver_settings` leaves them out (the surface
#: refit runs on the optimisation's result: :mod:`dipnet.solvers.surface_refit`).
UNRECORDED = frozenset({"progress", "checkpoint", "threshold", "surface_refit"})


class Checkpoint:
    """Saves and restores the state of :func:`~dipnet.solvers.optimize.optimise` stages.

    Args:
        directory: where the ``<stage>.pt`` files go (created when needed), e.g. the run directory.
        every: steps between saves (a stage's last step is always saved).
    """

    def __init__(self, directory: str | Path, every: int = 25) -> None:
        if int(every) < 1:
            raise ValueError(f"checkpoint every must be a positive number of steps, got {every!r}")
        self.directory, self.every = Path(directory), int(every)
        self._failed: set[Path] = set()

    def path(self, stage: str) -> Path:
        """The file of ``stage`` (a progress label such as ``"voxel 240^3"``)."""
        return self.directory / (re.sub(r"[^A-Za-z0-9_.-]+", "_", stage).strip("_") + ".pt")

    def restore(self, stage: str, fingerprint: dict, params: list[torch.Tensor], optimizer, scheduler,
                lagged: Mapping[str, Any] | None = None) -> tuple[int, dict[str, list[float]] | None, bool]:
        """Load ``stage``'s state into ``params`` / ``optimizer`` / ``scheduler`` and the priors ``lagged``
        (``{name: prior with lag_state / restore_lag}``, those whose :meth:`lag_state` is not ``None``) when its file
        holds a valid state of the problem ``fingerprint`` describes; returns ``(steps done,
        history, whether the stage had ended)`` (``(0, None, False)``: start afresh, with a warning
        naming the file when one was there but unusable)."""
        lagged = dict(lagged or {})
        file = self.path(stage)
        with suppress(OSError):  # what a kill mid-write left (the checkpoint itself is whole)
            _tmp(file).unlink(missing_ok=True)
        if not file.is_file():
            return 0, None, False
        state, problem = read_state(file)
        if problem is None:
            try:
                problem = _check_state(state, fingerprint, params, lagged)
            except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file, the stage starts afresh
                problem = _unreadable(file, exc)
        if problem is None:
            problem = _load_state(state, params, optimizer, scheduler)
        if problem is not None:
            _warn(f"checkpoint {file} is not used: {problem}; starting {stage!r} afresh")
            return 0, None, False
        if "lagged" in state:
            for name, prior in lagged.items():
                prior.restore_lag(state["lagged"][name])
        elif lagged:
            log.info("checkpoint %s predates the priors' lagged state: %s resume(s) with a fresh lag (the result "
                     "is near, not bit-identical to, an uninterrupted solve's)", file, ", ".join(sorted(lagged)))
        log.info("resumed %r from %s at step %d", stage, file, state["step"])
        return int(state["step"]), state["history"], bool(state["done"])

    def save(self, stage: str, fingerprint: dict, step: int, params: list[torch.Tensor], optimizer, scheduler,
             history: dict[str, list[float]], done: bool, lagged: Mapping[str, Any] | None = None) -> bool:
        """Write the state after ``step`` steps when ``step`` is a multiple of ``every`` or ``done``, with the
        :meth:`lag_state` of the priors ``lagged`` (``{name: prior}``, as :meth:`restore` takes them);
        returns whether it wrote (``False`` also when the write failed, with a warning)."""
        if not done and step % self.every:
            return False
        file = self.path(stage)
        state = {"fingerprint": fingerprint, "step": step, "done": done,
                 "params": [p.detach().clone() for p in params], "optimizer": optimizer.state_dict(),
                 "scheduler": None if scheduler is None else scheduler.state_dict(), "history": history,
                 "lagged": {name: prior.lag_state() for name, prior in (lagged or {}).items()}}
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            write_state(state, file)
        except (OSError, RuntimeError) as exc:  # torch.save reports a full disk as a RuntimeError
            if file not in self._failed:  # once per file: a full disk stays full
                self._failed.add(file)
                _warn(f"checkpoint {file} could not be written ({type(exc).__name__}: "
                      f"{' '.join(str(exc).split())[:200]}); the solve goes on, a rerun resumes from the "
                      "previous checkpoint (if any)")
            return False
        return True


def _tmp(file: Path) -> Path:
    """Where ``file`` is written before it is renamed into place."""
    return file.with_name(file.name + ".tmp")


def write_state(state: dict, file: Path) -> None:
    """``torch.save`` ``state`` to ``file`` atomically: a temporary file beside it, flushed to disk, renamed over
    ``file``, so a kill mid-write leaves the previous file whole (a failed write removes its temporary file).

    Raises:
        OSError, RuntimeError: the write failed (``torch.save`` reports a full disk as a ``RuntimeError``).
    """
    write_atomically(file, lambda stream: torch.save(state, stream), binary=True, tmp=_tmp(Path(file)))


def read_state(file: Path) -> tuple[Any, str | None]:
    """``(what file holds, None)``, read with ``torch.load(..., weights_only=True)`` (tensors, numbers, strings,
    lists and dicts only: nothing in the file runs), or ``(None, why it cannot be read)`` in a few words (empty,
    truncated, foreign bytes)."""
    try:
        with warnings.catch_warnings():  # torch's own notes on odd files: the caller's one message says it all
            warnings.simplefilter("ignore")
            return torch.load(file, map_location="cpu", weights_only=True), None
    except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file, it is not read
        return None, _unreadable(Path(file), exc)


def tensor_digest(*tensors: torch.Tensor | None) -> str:
    """The sha256 (16 hex characters) of ``tensors``' shapes and float64 values, in order (``None`` counts too): the
    fingerprint of a stage's measured data and directions. A sum, as before, matched other data with the same total:
    two dips' directions swapped, or two slabs, resumed the other measurement's finished solve, whose result came out
    with exit code 0."""
    sha = hashlib.sha256()
    for tensor in tensors:
        values = b"none" if tensor is None else tensor.detach().to("cpu", torch.float64).contiguous().numpy().tobytes()
        sha.update(repr(None if tensor is None else tuple(tensor.shape)).encode() + values)
    return sha.hexdigest()[:16]


def _check_state(state, fingerprint: dict, params: list[torch.Tensor], lagged: Mapping[str, Any] | None = None
                 ) -> str | None:
    """What makes ``state`` (a loaded checkpoint) unusable for ``params`` and the lagged priors' names ``lagged``
    of the problem ``fingerprint`` (which holds ``iterations`` and the loss ``terms``), or ``None`` when it fits
    (a record without the ``lagged`` field, :data:`LEGACY_FIELDS`, fits too)."""
    if not isinstance(state, dict) or set(state) not in (FIELDS, LEGACY_FIELDS):
        keys = sorted(map(str, state)) if isinstance(state, dict) else type(state).__name__
        return f"it is not a dipnet checkpoint (fields {keys})"
    recorded = state["fingerprint"]
    if recorded != fingerprint:
        same_problem = isinstance(recorded, dict) and set(recorded) == set(fingerprint) and all(
            recorded[key] == value for key, value in fingerprint.items() if key not in ("options", "weights"))
        if not same_problem:
            return "it was made for another problem (grid, operator, measured data or solver settings differ)"
        if recorded["weights"] != fingerprint["weights"]:
            return (f"it was made with other learned-prior weights (sha256 of their files {recorded['weights']} -> "
                    f"{fingerprint['weights']}: weights retrained under the same name?)")
        differences = _differences(recorded["options"], fingerprint["options"])
        return f"it was made with other solver options ({'; '.join(differences)} (recorded -> now))"
    saved, step, history = state["params"], state["step"], state["history"]
    if not (isinstance(saved, list) and len(saved) == len(params) and all(
            isinstance(s, torch.Tensor) and s.shape == p.shape and s.dtype == p.dtype
            for s, p in zip(saved, params))):
        return "its parameters do not match the solver's (number, shapes or dtypes)"
    if type(step) is not int or not 0 < step <= fingerprint["iterations"] or type(state["done"]) is not bool:
        return f"its step count {step!r} is out of range"
    if not (isinstance(history, dict) and list(history) == list(fingerprint["terms"])
            and all(isinstance(v, list) and len(v) == step for v in history.values())):
        return "its loss history does not match its step count and terms"
    if not isinstance(state["optimizer"], dict):
        return "it holds no optimiser state"
    if "lagged" in state and not _lag_fits(state["lagged"], set(lagged or {})):
        return "its priors' lagged state (a red mode learned prior's denoiser output) does not match the solver's"
    return None


def _lag_fits(recorded: Any, names: set[str]) -> bool:
    """Whether ``recorded`` (a checkpoint's ``lagged`` field) holds a lagged state (``{"calls": int >= 0,
    "denoised": tensor or None}``) for each of the priors ``names``, and for no other."""
    return isinstance(recorded, dict) and set(recorded) == names and all(
        isinstance(lag, dict) and set(lag) == {"calls", "denoised"} and type(lag["calls"]) is int
        and lag["calls"] >= 0 and (lag["denoised"] is None or isinstance(lag["denoised"], torch.Tensor))
        for lag in recorded.values())


def solver_settings(solver: Solver) -> dict[str, Any]:
    """The options of ``solver`` that shape its optimisation, as what a checkpoint can hold
    (numbers, strings, lists, dicts): ``{"class": class name, attribute: value, ...}``, a nested
    solver (a warm start) as its own settings, a tensor as its shape and sum, another object as its
    class name. Left out: fitted state (names ending in ``_``) and :data:`UNRECORDED`."""
    return {"class": type(solver).__name__, **{name: _recordable(value) for name, value in vars(solver).items()
                                               if name not in UNRECORDED and not name.startswith("_")
                                               and not name.endswith("_")}}


def _recordable(value: Any) -> Any:
    """``value`` as plain numbers, strings, lists and dicts (see :func:`solver_settings`)."""
    if isinstance(value, Solver):
        return solver_settings(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _recordable(dataclasses.asdict(value))
    if isinstance(value, Mapping):
        return {str(k): _recordable(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [_recordable(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, torch.Tensor):
        return f"tensor {list(value.shape)} sum {float(value.double().sum())!r}"
    return type(value).__qualname__


def _differences(recorded: Any, now: Any) -> list[str]:
    """The options that differ between two :func:`solver_settings` records, as
    ``"solver.<dotted name> <recorded> -> <now>"`` (``None``: not set)."""
    before, after = _leaves(recorded, "solver"), _leaves(now, "solver")
    return [f"{name} {before.get(name)!r} -> {after.get(name)!r}" for name in sorted(set(before) | set(after))
            if before.get(name) != after.get(name)]


def _leaves(value: Any, key: str) -> dict[str, Any]:
    """``{dotted key: value}`` of every leaf of ``value`` (itself when it is not a non-empty dict)."""
    if not isinstance(value, dict) or not value:
        return {key: value}
    return {k: v for name, child in value.items() for k, v in _leaves(child, f"{key}.{name}").items()}


def _unreadable(file: Path, exc: Exception) -> str:
    """Why checkpoint ``file`` could not be loaded (``exc``), in a few words."""
    if file.stat().st_size == 0:
        return "it is empty"
    if isinstance(exc, pickle.UnpicklingError) and "weights_only" in str(exc):
        return ("it is damaged or holds more than tensors, numbers, strings, lists and dicts (left unread: "
                "unpickling it could run code)")
    first = " ".join(next((line for line in str(exc).splitlines() if line.strip()), "").split())[:200]
    return f"it is damaged or truncated ({type(exc).__name__}{': ' + first if first else ''})"


def _load_state(state: dict, params: list[torch.Tensor], optimizer, scheduler) -> str | None:
    """Put a checked ``state`` into ``params``, ``optimizer`` and ``scheduler``; on failure put
    back what was there and say why."""
    before = ([p.detach().clone() for p in params], optimizer.state_dict(),
              None if scheduler is None else scheduler.state_dict())
    try:
        _put(state["params"], state["optimizer"], state["scheduler"], params, optimizer, scheduler)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as exc:
        _put(*before, params, optimizer, scheduler)
        return f"its optimiser state does not fit ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})"
    return None


def _put(values: list[torch.Tensor], optimizer_state: dict, scheduler_state: dict | None,
         params: list[torch.Tensor], optimizer, scheduler) -> None:
    with torch.no_grad():
        for p, value in zip(params, values):
            p.copy_(value)
    optimizer.load_state_dict(optimizer_state)
    if scheduler is not None:
        if not isinstance(scheduler_state, dict):
            raise TypeError("no scheduler state")
        scheduler.load_state_dict(scheduler_state)


def _warn(message: str) -> None:
    log_and_warn(log, message, stacklevel=4)


def checkpoint_directory(setting, run_dir: str | Path) -> Path | None:
    """The directory ``output.checkpoint`` names (``setting`` as :func:`attach_checkpoint` takes it), checked before
    any work: ``None`` for no checkpoint.

    Raises:
        ValueError: ``setting`` is not null, true or a directory, or the directory is a file or lies under one (every
            checkpoint write would fail, each with a warning, and the solve would go on without them).
    """
    if setting is None or setting is False:
        return None
    if setting is True:
        directory = Path(run_dir) / "checkpoints"
    elif isinstance(setting, (str, Path)) and str(setting).strip():
        directory = Path(setting)
    else:
        raise ValueError(f"output.checkpoint must be null, true or a directory, got {setting!r}")
    blocking = next((p for p in (directory, *directory.parents) if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"output.checkpoint={setting}: {blocking} is a file, not a directory, so no checkpoint "
                         f"could be written into {directory}: give a directory (made when needed), or true for "
                         "<run dir>/checkpoints")
    return directory


def attach_checkpoint(solver, setting, run_dir: str | Path, every: int = 25) -> Checkpoint | None:
    """Give ``solver`` the checkpoint the pipeline's ``output.checkpoint`` asks for.

    Args:
        solver: the instantiated solver; only solvers with a ``checkpoint`` attribute (the
            optimisation solvers, ``voxel`` and ``implicit``) can resume.
        setting: ``None`` / ``False``: none; ``True``: ``<run_dir>/checkpoints``; a path: that
            directory (so a rerun with the same path, or with the same ``hydra.run.dir`` and
            ``True``, continues the interrupted solve).
        run_dir: the job's output directory.
        every: steps between saves.

    Returns:
        The checkpoint given to the solver, or ``None``.
    """
    directory = checkpoint_directory(setting, run_dir)
    if directory is None:
        return None
    if not hasattr(solver, "checkpoint"):
        message = (f"output.checkpoint: solver {type(solver).__name__} does not checkpoint (the optimisation "
                   "solvers voxel and implicit do); ignored")
        log_and_warn(log, message, stacklevel=2)
        return None
    solver.checkpoint = Checkpoint(directory, every)
    log.info("checkpointing the solve to %s every %d steps (a rerun with it resumes)", directory, every)
    return solver.checkpoint
