"""On / off options read strictly: :func:`checked_flag`.

A config or a caller may give ``"no"`` for off, which Python reads as true (``bool("no")``): every on / off option of
the solvers and the rig's devices goes through :func:`checked_flag`, which refuses anything but true or false.
"""

from __future__ import annotations

import numbers

import numpy as np


def checked_flag(name: str, value) -> bool:
    """The on / off option ``name`` as a bool: ``True`` or ``False`` (or the integers 1 and 0); anything else
    raises a ``ValueError`` naming ``name`` (a string such as ``"no"`` was read as on)."""
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, numbers.Integral) and value in (0, 1)):
        return bool(value)
    raise ValueError(f"{name} must be true or false, got {value!r}")
