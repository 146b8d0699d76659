"""Counts given as options: whole numbers, never silently cut (``iterations=2.5`` would run 2 unsaid)."""

from __future__ import annotations

import math
import numbers
from typing import Any


def whole_number(name: str, value: Any, low: int | None = None) -> int:
    """``value`` (the option ``name``, a count) as an int.

    Raises:
        ValueError: naming the option, unless ``value`` is a finite whole number (``3.0`` is 3; ``2.5``, ``True``
            and ``"3"`` are refused, not cut or parsed), at least ``low`` when given.
    """
    if isinstance(value, (bool, str)) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
            or value != int(value):
        raise ValueError(f"{name} must be a whole number, got {value!r} (2.5 is not cut to 2)")
    if low is not None and value < low:
        raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
    return int(value)
