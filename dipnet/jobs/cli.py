"""Helpers for the command-line entry points: one error contract for every script.

Every bad input (a malformed file, an out-of-range option, an unknown config choice such as
``solver=foo``, an unparsable override, a required option left unset) ends in one line
``error: ...`` naming the file (and line) or the option, and exit code 2:

* :func:`run_hydra` runs a ``@hydra.main`` function so that Hydra's composition errors reach
  :func:`user_errors` instead of Hydra's multi-line report with exit code 1;
* :func:`require_options` names the options still ``???`` in a composed config;
* :func:`user_errors` turns the user-error exceptions (a missing pip extra among them) into the one line;
* :func:`~dipnet.core.console.interrupted` turns Ctrl-C into one line saying how to resume, and exit code
  130, and :func:`~dipnet.core.console.report` shows such a line once on the terminal and records it in the
  job's log file (in :mod:`dipnet.core.console`, as every room's entry points use them).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from hydra.errors import HydraException, InstantiationException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dipnet.core.console import report
from dipnet.core.keywords import accepted_keywords
from dipnet.core.optional import MissingExtraError
from dipnet.jobs.warnings_once import log_warnings_once

log = logging.getLogger("dipnet")

#: Exceptions that mean "the user's input is wrong" (or an optional package the chosen option needs is
#: missing: the message names the pip extra), reported in one line, not a traceback.
#: Set DIPNET_DEBUG=1 to get the full traceback instead.
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, KeyError, MissingExtraError, HydraException,
                                                OmegaConfBaseException)


class MissingOptionError(ValueError):
    """A required config option (``???``) was not given."""


def error_message(exc: BaseException) -> str:
    """The one-line message for ``exc``; a failed instantiation reports the user error behind it."""
    cause = exc.__cause__
    if isinstance(exc, InstantiationException) and isinstance(cause, USER_ERRORS):
        return _leaf_named(error_message(cause), exc)
    if isinstance(exc, InstantiationException) and isinstance(cause, TypeError):  # e.g. shape.radius=abc
        found = re.search(r"full_key: (\S+)", str(exc))  # Hydra names the node only in its message
        node = found.group(1) if found else "a config node"
        return (f"{node}: an option of the wrong type ({cause}): check the values given to {node}.* "
                "(a number written as text, a list where one value is expected, ...)")
    if isinstance(exc, KeyError) and exc.args:
        return f"missing key {exc.args[0]!r}"
    if isinstance(cause, OSError) and cause.filename and str(exc).startswith("Unable to configure handler"):
        return (f"the run directory {Path(cause.filename).parent} is not writable (its log file "
                f"{cause.filename}: {cause.strerror or cause}): make it writable or choose another with "
                f"hydra.run.dir=...")
    maker = _making_run_dir(exc) if isinstance(exc, OSError) and exc.filename else None
    if maker is not None:  # was "/tmp/x: File exists", naming no option
        return run_dir_message(exc, maker)
    if isinstance(exc, OSError) and exc.filename and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    text = str(exc).split("Config search path:")[0]  # Hydra appends its search path to composition errors
    text = " ".join(text.split()) or type(exc).__name__
    if "Could not find 'hydra/launcher/" in text:
        text += ' (the joblib and submitit launchers come with pip install "dipnet[sweeps]")'
    return text


def _leaf_named(message: str, exc: InstantiationException) -> str:
    """``message`` (of the error a target raised) with the option it opens with named by its path in the config:
    ``protocol clearance_mm must be ...`` for the node ``source.simulator.protocol`` reads
    ``source.simulator.protocol.clearance_mm must be ...``. The option is a keyword the target takes
    (:func:`~dipnet.core.keywords.accepted_keywords`), alone or after the node's own name (``shape radius``,
    ``shape.axis``); any other message is returned as it is."""
    from hydra._internal.utils import _locate

    node = re.search(r"full_key: (\S+)", str(exc))  # Hydra names the node and the target only in its message
    target = re.search(r"call to target '([^']+)'", str(exc))
    if node is None or target is None:
        return message
    try:
        keys = accepted_keywords(_locate(target.group(1))) or set()
    except (ImportError, ValueError, TypeError):  # a target that cannot be located or inspected: as it is
        return message
    path = node.group(1)
    opening = re.match(rf"(?:{re.escape(path.rsplit('.', 1)[-1])}[ .])?(\w+)\b", message)
    if opening is None or opening.group(1) not in keys:
        return message
    return f"{path}.{opening.group(1)}{message[opening.end():]}"


def _making_run_dir(exc: OSError) -> str | None:
    """``"run_job"`` or ``"sweep"`` when ``exc`` was raised by Hydra creating a job's run directory (``run_job``'s
    ``mkdir``, before the job starts) or a sweep's folder (the sweeper's ``mkdir``), not by the job: the innermost
    frame outside ``pathlib`` and ``os`` is that Hydra function; else None."""
    frames = [frame for frame, _ in traceback.walk_tb(exc.__traceback__)
              if Path(frame.f_code.co_filename).name not in ("pathlib.py", "os.py")]
    if frames and frames[-1].f_code.co_name in ("run_job", "sweep") and \
            "hydra" in Path(frames[-1].f_code.co_filename).parts:
        return frames[-1].f_code.co_name
    return None


def run_dir_message(exc: OSError, maker: str = "run_job") -> str:
    """The one line for a run (``maker="run_job"``) or sweep (``"sweep"``) directory Hydra cannot create
    (``exc.filename``): a file in its place or above it, a missing or read-only parent, named with the option that
    chooses it."""
    path = Path(exc.filename)
    blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    why = f"{blocking} is a file, not a folder" if blocking is not None else f"{exc.strerror or exc}"
    option = "hydra.sweep.dir=..." if maker == "sweep" else \
        "hydra.run.dir=... (hydra.sweep.dir=... for a sweep, -m)"
    kind = "sweep directory" if maker == "sweep" else "run directory"
    return f"cannot create the {kind} {path} ({why}): choose a folder you can write with {option}"


@contextlib.contextmanager
def user_errors(exit_code: int = 2) -> Iterator[None]:
    """Turn bad-input exceptions into a one-line ``error: ...`` message and exit ``exit_code``."""
    try:
        yield
    except USER_ERRORS as exc:
        if os.environ.get("DIPNET_DEBUG"):
            raise
        report(f"error: {error_message(exc)}")
        raise SystemExit(exit_code) from None


def run_hydra(main: Callable[[], Any]) -> Any:
    """Call the ``@hydra.main``-decorated ``main`` under :func:`user_errors`.

    Hydra reports its own errors (unknown config choice, bad override, missing config) in
    several lines and exits 1 unless ``HYDRA_FULL_ERROR`` is set, in which case it re-raises
    them: we set it, so they arrive here as exceptions and become the one-line error.

    A log handler that cannot write (the log file's disk is full) stays quiet instead of printing
    a traceback per record (``logging.raiseExceptions``), so the one line that says what happened
    (e.g. a scan's safe stop) is not buried. Each warning is shown once, through logging
    (:func:`~dipnet.jobs.warnings_once.log_warnings_once`).
    """
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    log_warnings_once()
    raise_exceptions, logging.raiseExceptions = logging.raiseExceptions, False
    try:
        with user_errors():
            return main()
    finally:
        logging.raiseExceptions = raise_exceptions


def require_options(cfg: DictConfig) -> None:
    """Raise :class:`MissingOptionError` naming every option of ``cfg`` still ``???``."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise MissingOptionError(f"option {', '.join(missing)} is required: set it on the command line, "
                                 f"e.g. {missing[0]}=...")
