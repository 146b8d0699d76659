"""Optional dependencies: import one, or say which pip extra brings it.

The core install (``pip install dipnet``) leaves out what only some users need; the extras
declared in ``pyproject.toml`` add it:

* ``rig``: ``minimalmodbus`` for Modbus RTU level sensors (``sensor=modbus``);
* ``repair``: ``networkx`` (winding and hole repair of broken meshes) and ``manifold3d``
  (merging overlapping mesh shells);
* ``sweeps``: ``optuna`` and Hydra's launchers for sweeps and tuning.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class MissingExtraError(ImportError):
    """An optional package is missing; the message names the extra that installs it."""


def optional_import(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` (a dotted name), or raise :class:`MissingExtraError` naming ``extra``.

    Args:
        module: the module to import, e.g. ``"minimalmodbus"``.
        extra: the ``dipnet`` extra that installs it, e.g. ``"rig"``.
        purpose: what needs it, completing "... needs <module>", e.g. ``"a Modbus level sensor"``.

    Returns:
        The imported module.
    """
    try:
        return importlib.import_module(module)
    except ImportError as err:
        top = module.split(".")[0]
        raise MissingExtraError(
            f"{purpose} needs {top}, which the core install leaves out: "
            f'pip install "dipnet[{extra}]"  (from a clone: pip install -e ".[{extra}]")'
        ) from err
