"""The code version of cached results: a digest of some packages' sources."""

from __future__ import annotations

import pytest

from dipnet.core.code_version import SIMULATION_PACKAGES, simulation_digest, source_digest


@pytest.fixture
def package(tmp_path, monkeypatch):
    """An importable package ``fakepkg`` with two modules, in ``tmp_path``."""
    root = tmp_path / "fakepkg"
    (root / "sub").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "sub" / "__init__.py").write_text("")
    (root / "sub" / "physics.py").write_text("G = 9.81\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return root


def test_the_digest_follows_every_edit_addition_and_rename(package):
    first = source_digest("fakepkg")
    assert len(first) == 12 and source_digest("fakepkg") == first  # deterministic
    (package / "sub" / "physics.py").write_text("G = 9.80665\n")
    edited = source_digest("fakepkg")
    (package / "extra.py").write_text("")
    added = source_digest("fakepkg")
    (package / "extra.py").rename(package / "other.py")
    renamed = source_digest("fakepkg")
    assert len({first, edited, added, renamed}) == 4
    (package / "notes.txt").write_text("not code")
    assert source_digest("fakepkg") == renamed  # only Python sources count


def test_the_simulation_digest_covers_the_simulator_and_what_it_imports():
    assert set(SIMULATION_PACKAGES) >= {"dipnet.simulator", "dipnet.shapes", "dipnet.core"}
    assert simulation_digest() == source_digest(*SIMULATION_PACKAGES)
    with pytest.raises(ValueError, match="not an importable package"):
        source_digest("dipnet.core.grid")  # a module, not a package
