"""Fixtures of the experiments tests: the learned prior's training pairs, made once per session."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import dipnet.experiments.prior_pairs as prior_pairs


@pytest.fixture(scope="session")
def _pair_store(tmp_path_factory) -> tuple[Path, dict]:
    """A session-wide directory of first-stage pair files (by their cache file name) and a dict of the
    generated shapes made so far (by ``(seed, family, radius)``)."""
    return tmp_path_factory.mktemp("pair_store"), {}


@pytest.fixture
def generated(_pair_store):
    """``generated_shape(seed, family=None, radius=45.0)`` made once per session for each arguments (a
    128^3 marching-cubes mesh, ~3 s): the very objects :func:`shared_pairs` hands the training pairs."""
    from dipnet.shapes.procedural import generated_shape

    shapes = _pair_store[1]

    def shape(seed: int, family: str | None = None, radius: float = 45.0, **more):
        if more:
            return generated_shape(seed, family=family, radius=radius, **more)
        key = (int(seed), family, float(radius))
        if key not in shapes:
            shapes[key] = generated_shape(seed, family=family, radius=radius)
        return shapes[key]

    return shape


@pytest.fixture
def shared_pairs(_pair_store, generated, monkeypatch) -> None:
    """Make each first-stage training pair and each generated shape once per session, not once per test.

    A pair's cache file name holds the digest of everything that makes it (seed, noise level, grid, dips,
    solver options, family, the mesh file's bytes, the code version: see
    :func:`~dipnet.experiments.prior_pairs.build_pairs`), so a pair made by an earlier test under that name
    is the pair this test would make: it is copied into the test's cache instead of being made again.
    ``build_pairs`` still decides which files are missing, names them and reads them back, and a test's
    cache holds exactly the files it asked for; only identical recomputation is saved. A file name not
    seen before is made by the real ``_make_and_save``. Second-stage inputs (``refine``) are always made
    afresh (no two tests share one, and a test may stub ``refine_input``). ``generated_shape`` (a 128^3
    marching-cubes mesh, ~3 s of a pair's ~4.5 s) is deterministic in its arguments and only read, so one
    object per ``(seed, family, radius)`` serves every pair of that shape (both noise levels, the second
    stage, and ``make_pair`` called directly).

    Not for ``workers > 1``: the spawned workers pickle ``_make_and_save`` by name.
    """
    store = _pair_store[0]
    make_and_save = prior_pairs._make_and_save

    def make_or_copy(file: Path, seed: int, snr_db, options: dict, refine=None, first=None) -> None:
        if refine is not None:
            make_and_save(file, seed, snr_db, options, refine, first)
            return
        stored = store / Path(file).name
        if not stored.is_file():
            make_and_save(stored, seed, snr_db, options)
        Path(file).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(stored, file)

    monkeypatch.setattr(prior_pairs, "_make_and_save", make_or_copy)
    monkeypatch.setattr(prior_pairs, "generated_shape", generated)
