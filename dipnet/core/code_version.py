"""A digest of the source code of some packages: the code version in the key of a result cache.

A cache of simulated measurements keyed only by its parameters would hand back old dips after a
change to the simulator; adding :func:`source_digest` of the packages that made them to the key
makes a rerun after any edit to them simulate afresh.
"""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path


def package_dir(package: str) -> Path:
    """The folder of an importable package, e.g. ``"dipnet.simulator"``."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise ValueError(f"{package!r} is not an importable package")
    return Path(next(iter(spec.submodule_search_locations)))


def source_digest(*packages: str, length: int = 12) -> str:
    """Hex digest (``length`` characters) of every ``.py`` file under ``packages``: their paths
    relative to each package folder and their bytes, in sorted order, so any edit, added, removed
    or renamed module changes it."""
    h = hashlib.sha256()
    for package in sorted(packages):
        root = package_dir(package)
        for path in sorted(root.rglob("*.py")):
            h.update(f"{package}/{path.relative_to(root).as_posix()}\0".encode())
            h.update(path.read_bytes())
            h.update(b"\0")
    return h.hexdigest()[:length]


#: What a simulated measurement depends on: the shapes (dips and truth occupancy), the simulator
#: (stage, tank, sensor), the preprocessing it ends with, and the core types (grid, orientations,
#: measurement format). The operators are not among them: they only reconstruct.
SIMULATION_PACKAGES = ("dipnet.core", "dipnet.preprocessing", "dipnet.shapes", "dipnet.simulator")


def simulation_digest() -> str:
    """:func:`source_digest` of :data:`SIMULATION_PACKAGES`: the code version of simulated dips."""
    return source_digest(*SIMULATION_PACKAGES)
