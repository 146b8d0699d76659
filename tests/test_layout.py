"""The test tree mirrors the package: every module has a test file found from its path (docs/development.md,
"Tests"), and test and helper basenames are unique (pytest imports them by basename: no ``__init__.py``
in tests/)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE, TESTS = ROOT / "dipnet", ROOT / "tests"
NOT_MODULES = ("__init__.py", "__main__.py")


def mirror_files(module: Path) -> list[Path]:
    """The test files of ``dipnet/<room>/<name>.py``: in ``tests/<room>/``, ``test_<name>.py``, or
    ``test_<room>_<name>.py`` when that basename is taken elsewhere in the tree (``<room>`` the module's
    own folder: ``fake`` for ``dipnet/rig/fake/grbl.py``, ``dipnet`` for ``dipnet/report.py``), or
    ``test_<name>_<concern>.py`` for a module with more than one."""
    folder = TESTS / module.parent.relative_to(PACKAGE)
    name = module.stem
    found = [folder / f"test_{name}.py", folder / f"test_{module.parent.name}_{name}.py"]
    return [p for p in found if p.is_file()] + sorted(folder.glob(f"test_{name}_*.py"))


def test_every_module_has_a_test_file_found_from_its_path():
    modules = sorted(p for p in PACKAGE.rglob("*.py") if p.name not in NOT_MODULES)
    assert len(modules) > 50  # the walk sees the package
    missing = [str(m.relative_to(ROOT)) for m in modules if not mirror_files(m)]
    assert not missing, ("modules without a test file (tests/<room>/test_<module>.py, or test_<room>_<module>.py, "
                         "see docs/development.md): " + ", ".join(missing))


def test_test_and_helper_basenames_are_unique():
    """conftest.py files excepted: pytest loads each of them by its path."""
    counts = Counter(p.name for p in TESTS.rglob("*.py") if p.name != "conftest.py")
    assert not {name: n for name, n in counts.items() if n > 1}
