"""Checkpoints of a long optimisation, so that an interrupted solve continues where it stopped.

:class:`Checkpoint` is handed to a solver (``OptimisationSolver(checkpoint=...)``); the
optimisation loop (:func:`dipnet.solvers.optimize.optimise`) calls :meth:`Checkpoint.restore`
before its first step and :meth:`Checkpoint.save` after every step. Every ``every`` steps, and
when a stage ends, it writes the parameters, the optimiser's and scheduler's state and the loss
history to ``<directory>/<stage>.pt`` (written to a temporary file, then renamed, so a kill
mid-write leaves the previous checkpoint intact). A finished stage is marked done, so a resumed
multi-stage solve (coarse then fine) skips it.

Adam and the schedules are deterministic, so a resumed solve gives the same result as an
uninterrupted one (to rounding). A checkpoint made for another problem (other parameter
shapes, step count or measured data) is ignored with a warning.
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path

import torch

log = logging.getLogger(__name__)


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

    def path(self, stage: str) -> Path:
        """The file of ``stage`` (a progress label such as ``"voxel 240^3"``)."""
        return self.directory / (re.sub(r"[^A-Za-z0-9_.-]+", "_", stage).strip("_") + ".pt")

    def restore(self, stage: str, fingerprint: dict, params: list[torch.Tensor], optimizer, scheduler
                ) -> tuple[int, dict[str, list[float]] | None, bool]:
        """Load ``stage``'s state into ``params`` / ``optimizer`` / ``scheduler`` when its file
        matches ``fingerprint``; returns ``(steps done, history, whether the stage had ended)``
        (``(0, None, False)``: start afresh)."""
        file = self.path(stage)
        if not file.is_file():
            return 0, None, False
        state = torch.load(file, weights_only=False)
        if state.get("fingerprint") != fingerprint:
            message = f"checkpoint {file} was made for another problem; starting {stage!r} afresh"
            log.warning(message)
            warnings.warn(message, stacklevel=3)
            return 0, None, False
        with torch.no_grad():
            for p, saved in zip(params, state["params"]):
                p.copy_(saved)
        optimizer.load_state_dict(state["optimizer"])
        if scheduler is not None:
            scheduler.load_state_dict(state["scheduler"])
        log.info("resumed %r from %s at step %d", stage, file, state["step"])
        return int(state["step"]), state["history"], bool(state["done"])

    def save(self, stage: str, fingerprint: dict, step: int, params: list[torch.Tensor], optimizer, scheduler,
             history: dict[str, list[float]], done: bool) -> bool:
        """Write the state after ``step`` steps when ``step`` is a multiple of ``every`` or ``done``;
        returns whether it wrote."""
        if not done and step % self.every:
            return False
        file = self.path(stage)
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = file.with_suffix(".tmp")
        torch.save({"fingerprint": fingerprint, "step": step, "done": done,
                    "params": [p.detach().clone() for p in params], "optimizer": optimizer.state_dict(),
                    "scheduler": None if scheduler is None else scheduler.state_dict(), "history": history}, tmp)
        tmp.replace(file)
        return True


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
    if setting is None or setting is False:
        return None
    if setting is True:
        directory = Path(run_dir) / "checkpoints"
    elif isinstance(setting, (str, Path)) and str(setting).strip():
        directory = Path(setting)
    else:
        raise ValueError(f"output.checkpoint must be null, true or a directory, got {setting!r}")
    if not hasattr(solver, "checkpoint"):
        message = (f"output.checkpoint: solver {type(solver).__name__} does not checkpoint (the optimisation "
                   "solvers voxel and implicit do); ignored")
        log.warning(message)
        warnings.warn(message, stacklevel=2)
        return None
    solver.checkpoint = Checkpoint(directory, every)
    log.info("checkpointing the solve to %s every %d steps (a rerun with it resumes)", directory, every)
    return solver.checkpoint
