"""Strict JSON for every ``.json`` file dipnet writes: non-finite numbers are written as ``null``.

Python's :mod:`json` writes NaN and infinities as the bare words ``NaN`` / ``Infinity``, which
are not JSON: a browser's ``JSON.parse``, ``jq`` and most other readers reject the whole file.
:func:`dumps` writes them as ``null`` instead (and refuses any other non-finite value,
``allow_nan=False``); dipnet's readers take ``null`` as "no value", as they took NaN.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, +-inf; also inside dicts, lists and tuples)
    replaced by ``None``; tuples become lists, everything else is returned unchanged."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(item) for item in value]
    return value


def dumps(obj: Any, **kwargs: Any) -> str:
    """``obj`` as strict JSON text (non-finite numbers as ``null``); ``kwargs`` go to :func:`json.dumps`
    (``indent``, ``sort_keys``, ``default``, ...)."""
    return json.dumps(finite_or_none(obj), allow_nan=False, **kwargs)


def write_json(path: str | Path, obj: Any, **kwargs: Any) -> Path:
    """Write ``obj`` to ``path`` as strict JSON (:func:`dumps` with ``kwargs``) ending in a newline;
    returns the path."""
    path = Path(path)
    path.write_text(dumps(obj, **kwargs) + "\n")
    return path
