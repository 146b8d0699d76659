"""Load an entry-point script (``scripts/<name>.py``) or any other file as a module, for the tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"


def load_module(path: Path, name: str) -> ModuleType:
    """Execute the file ``path`` as module ``name`` (registered in ``sys.modules``: dataclasses and
    pickling look their module up there) and return it."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` as a module."""
    return load_module(SCRIPTS / f"{name}.py", name)
