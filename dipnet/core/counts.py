"""Numbers given as options: :func:`is_real` (no boolean or text passes for one) and :func:`whole_number` (counts,
never silently cut: ``iterations=2.5`` would run 2 unsaid)."""

from __future__ import annotations

import math
import numbers
from typing import Any


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number: not a boolean (``True`` is 1 to Python, so ``step_mm=true`` ran a 1 mm
    step), text or a complex number. NaN and infinities pass: a caller checks its range."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def whole_number(name: str, value: Any, low: int | None = None) -> int:
    """``value`` (the option ``name``, a count) as an int.

    Raises:
        ValueError: naming the option, unless ``value`` is a finite whole number (``3.0`` is 3; ``2.5``, ``True``
            and ``"3"`` are refused, not cut or parsed), at least ``low`` when given.
    """
    if not is_real(value) or not math.isfinite(value) \
            or value != int(value):
        cut = " (2.5 is not cut to 2)" if is_real(value) and math.isfinite(value) else ""  # not for 'abc', nan
        raise ValueError(f"{name} must be a whole number, got {value!r}{cut}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
    return int(value)
