"""Exclusive cross-process locks (Linux, macOS, Windows) for files and run directories.

One mechanism, :class:`HeldLock`, for everything a second process must not share: a raw scan
file being written (:class:`dipnet.core.rawscan_writer.RawScanWriter`), a serial port
(:class:`dipnet.rig.controller.PortLock`), a job's output directory (:func:`run_directory_lock`,
entered by ``scripts/reconstruct.py`` and ``scripts/scan.py``) and a solve's checkpoint directory
(:func:`checkpoint_directory_lock`, held by :func:`dipnet.jobs.pipeline.run` while it solves).
The lock is the maintained ``filelock`` package's OS lock on a lock file (``flock`` on Unix, ``LockFileEx`` on Windows),
released by the operating system when the process dies, so a crash never leaves a stale lock.
Beside it the holder writes who it is (pid, host, start time) into ``<lock file>.holder``, so a
refused second process can say whom it waits for; that file is removed on release.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from filelock import FileLock, Timeout

#: The lock file a job locks in its run directory while it runs. On Linux and macOS the empty file stays after
#: the job (a rejected one too): it is harmless, the lock being the OS lock on it, and deleting it on release
#: would let a process that opened it just before lock the deleted file while a third one locks a new one.
RUN_LOCK_NAME = ".dipnet-run.lock"
#: The lock file a solve locks in its checkpoint directory (``output.checkpoint``) while it solves.
CHECKPOINT_LOCK_NAME = ".dipnet-checkpoint.lock"


class LockHeld(OSError):
    """Another process (or another writer in this one) holds the lock; the message names the holder."""


class HeldLock:
    """An exclusive lock on ``path`` (a lock file, created when needed), taken at once or refused.

    Args:
        path: the lock file.

    Raises:
        LockHeld: someone else holds it; the message is the holder as it wrote itself, e.g.
            ``"pid 4242 on rig-pc, since 2026-11-23T16:10:00+0100"``.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.holder_path = self.path.with_name(self.path.name + ".holder")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock: FileLock | None = FileLock(str(self.path), thread_local=False)
        try:
            self._lock.acquire(timeout=0)
        except Timeout:
            self._lock = None
            raise LockHeld(self.holder()) from None
        with suppress(OSError):  # the holder's identity is a courtesy to the next process, never a failure
            self.holder_path.write_text(f"pid {os.getpid()} on {socket.gethostname()}, "
                                        f"since {time.strftime('%Y-%m-%dT%H:%M:%S%z')}\n", encoding="utf-8")

    def holder(self) -> str:
        """Who holds the lock, as its holder wrote it (``"another process"`` when unknown)."""
        try:
            text = self.holder_path.read_text(encoding="utf-8", errors="replace").strip()
        except OSError:
            text = ""
        return text or "another process"

    def release(self) -> None:
        """Give the lock up (idempotent)."""
        if self._lock is not None:
            with suppress(OSError):
                self.holder_path.unlink()
            self._lock.release()
            self._lock = None


@contextmanager
def _held_directory(directory: Path, lock_name: str, refused: Callable[[LockHeld], str]) -> Iterator[Path]:
    """Hold ``directory`` (created when needed) by its lock file ``lock_name`` for the ``with`` block; when another
    process holds it, raise :class:`LockHeld` with the message ``refused(holder)``."""
    try:
        lock = HeldLock(directory / lock_name)
    except LockHeld as exc:
        raise LockHeld(refused(exc)) from None
    try:
        yield directory
    finally:
        lock.release()


@contextmanager
def run_directory_lock(directory: str | Path) -> Iterator[Path]:
    """Hold ``directory`` (a job's output directory, created when needed) for the ``with`` block.

    Two jobs writing into one directory would overwrite each other's files (and a checkpoint
    resume would read a half-written state); the second one is refused before it writes anything.

    Raises:
        LockHeld: another job runs in ``directory``; the one-line message names it (pid, host,
            start time) and says what to do.
    """
    directory = Path(directory)
    with _held_directory(directory, RUN_LOCK_NAME, lambda holder: (
            f"run directory {directory} is in use by another job ({holder}): wait for it to finish, stop it, or "
            "choose another output directory (hydra.run.dir=...)")) as held:
        yield held


@contextmanager
def checkpoint_directory_lock(directory: str | Path | None) -> Iterator[Path | None]:
    """Hold ``directory`` (a solve's checkpoint directory, created when needed; ``None``: nothing to hold) for the
    ``with`` block.

    ``output.checkpoint=DIR`` may name one directory for several jobs; two solving at once would overwrite each
    other's ``<stage>.pt`` files, each then ignoring the other's on a resume: the second one is refused before it
    solves.

    Raises:
        LockHeld: another solve checkpoints into ``directory``; the message names it and says what to do.
    """
    if directory is None:
        yield None
        return
    directory = Path(directory)
    with _held_directory(directory, CHECKPOINT_LOCK_NAME, lambda holder: (
            f"checkpoint directory {directory} is in use by another solve ({holder}): two solves checkpointing into "
            "one directory would overwrite each other's checkpoints; wait for it to finish, or give this job its own "
            "(output.checkpoint=true: <run dir>/checkpoints)")) as held:
        yield held
