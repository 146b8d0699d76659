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


class DuplicateKeyError(ValueError):
    """A JSON object (or YAML mapping) of a file names one key twice."""


def unique_keys(pairs: list[tuple[Any, Any]]) -> dict:
    """A mapping from ``pairs`` (``json.loads(..., object_pairs_hook=unique_keys)``), refusing a key given twice:
    JSON and YAML readers keep the last silently, so a hand-edited file read another value than the one its
    author saw first.

    Raises:
        DuplicateKeyError: naming the key and both values.
    """
    data: dict = {}
    for key, value in pairs:
        if key in data:
            raise DuplicateKeyError(f"key {key!r} is given twice ({data[key]!r} and {value!r}): keep one")
        data[key] = value
    return data


def write_json(path: str | Path, obj: Any, **kwargs: Any) -> Path:
    """Write ``obj`` to ``path`` as strict JSON (:func:`dumps` with ``kwargs``) ending in a newline;
    returns the path."""
    path = Path(path)
    path.write_text(dumps(obj, **kwargs) + "\n")
    return path
