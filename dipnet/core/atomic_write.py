"""Files written whole or not at all: the bytes go to a temporary file beside the target, are flushed to disk and
renamed over it (``os.replace``, atomic on one file system), so a run killed mid-write leaves the previous file
whole and no file cut short."""

from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import IO


def write_atomically(path: str | Path, write: Callable[[IO], None], *, binary: bool = False,
                     tmp: Path | None = None) -> Path:
    """Call ``write(stream)`` on a temporary file (``tmp``, default ``.<name>.tmp`` beside ``path``), fsync it and
    rename it over ``path``; on any error (a full disk, an interrupt) the temporary file is removed and the error
    raised. Returns ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp") if tmp is None else tmp
    try:
        with open(tmp, "wb" if binary else "w", **({} if binary else {"encoding": "utf-8"})) as stream:
            write(stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        with suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    return path
