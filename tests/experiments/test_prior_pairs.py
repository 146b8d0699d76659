"""Training pairs of the learned prior: simulated like the benchmark, both noise levels, cached."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere
from dipnet.experiments.prior_pairs import build_pairs, make_pair, plan_directions, refine_weights_digest, rotated_mesh
from dipnet.shapes.procedural import family_of
from dipnet.solvers.denoiser import PriorWeightsError

SMALL = {"n": 16, "dips": 8, "solver_options": {"iterations": 10}, "progress": False}


def test_one_pair_per_seed_and_noise_level_cached_and_bounded(tmp_path, shared_pairs):
    x, y = build_pairs([5000, 5001], cache=tmp_path, noise_levels=(None, 30.0), **SMALL)
    assert x.shape == y.shape == (4, 16, 16, 16) and len(list(tmp_path.glob("pair_*.npz"))) == 4
    assert 0 <= x.min() and x.max() <= 1 and 0 <= y.min() and y.max() <= 1
    assert np.array_equal(y[0], y[1]) and not np.array_equal(x[0], x[1])  # same truth, noisy input differs
    x2, _ = build_pairs([5000, 5001], cache=tmp_path, noise_levels=(None, 30.0), **SMALL)
    assert np.array_equal(x, x2)


def test_a_code_change_makes_the_pairs_afresh(tmp_path, shared_pairs, monkeypatch):
    import dipnet.experiments.prior_pairs as prior_pairs

    build_pairs([5000], cache=tmp_path, noise_levels=(None,), **SMALL)
    monkeypatch.setattr(prior_pairs, "pairs_code", lambda: "another-version")
    build_pairs([5000], cache=tmp_path, noise_levels=(None,), **SMALL)
    assert len(list(tmp_path.glob("pair_*.npz"))) == 2  # the old pair is not handed back


def test_target_is_the_partial_volume_of_the_generated_solid(tmp_path, shared_pairs, generated):
    _, y = build_pairs([5002], cache=tmp_path, noise_levels=(None,), **SMALL)
    grid = Grid(16, 3)
    shape = generated(5002, radius=0.9 * grid.radius)  # generated_shape, made once per session
    volume = float(y.sum()) * grid.voxel_volume
    assert abs(volume / abs(shape.mesh.volume) - 1) < 0.05
    assert ((y > 0) & (y < 1)).any()  # soft at the surface, not a binary mask


def test_a_named_family_makes_that_familys_solid_and_its_own_pairs(tmp_path, shared_pairs, generated):
    """``family`` replaces the family the seed draws; the seed's own pair keeps its cache file."""
    _, own = build_pairs([5002], cache=tmp_path, noise_levels=(None,), **SMALL)
    _, organic = build_pairs([5002], cache=tmp_path, noise_levels=(None,), family="organic", **SMALL)
    grid = Grid(16, 3)
    shape = generated(5002, family="organic", radius=0.9 * grid.radius)  # generated_shape, made once per session
    assert family_of(5002) != "organic" and not np.array_equal(own, organic)  # the family the seed draws
    assert abs(float(organic.sum()) * grid.voxel_volume / abs(shape.mesh.volume) - 1) < 0.05
    assert len(list(tmp_path.glob("pair_*.npz"))) == 2


@pytest.fixture
def box_file(tmp_path):
    """A 2 x 1 x 0.5 box (volume 1) as a PLY file."""
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(2.0, 1.0, 0.5)).export(path)
    return path


def test_a_rotated_mesh_is_turned_by_its_seed_and_scaled_to_the_radius(box_file):
    """The box's farthest corner is at ``radius``, so its volume is known; the seed fixes the turn."""
    radius = 10.0
    scale = radius / np.sqrt(1.0**2 + 0.5**2 + 0.25**2)  # the half-diagonal of the box -> radius
    shapes = [rotated_mesh(box_file, seed, radius) for seed in (0, 0, 1)]
    for shape in shapes:
        assert np.linalg.norm(shape.mesh.vertices, axis=1).max() == pytest.approx(radius)
        assert shape.volume == pytest.approx(scale**3, rel=1e-9)
    assert np.allclose(shapes[0].mesh.vertices, shapes[1].mesh.vertices)
    assert not np.allclose(shapes[0].mesh.vertices, shapes[2].mesh.vertices)


def test_mesh_pairs_have_its_volume_and_their_own_cache_files_keyed_by_its_bytes(tmp_path, shared_pairs, box_file):
    """A mesh pair's target is the turned mesh's partial volume; its cache file is named after the
    mesh and keyed by the file's bytes (not its path), beside the generated seeds' own files."""
    cache = tmp_path / "cache"
    build_pairs([5000], cache=cache, noise_levels=(None,), **SMALL)
    x, y = build_pairs([0, 1], cache=cache, noise_levels=(None,), mesh=box_file, **SMALL)
    grid = Grid(16, 3)
    for seed, target in zip((0, 1), y):
        volume = rotated_mesh(box_file, seed, 0.9 * grid.radius).volume
        assert abs(float(target.sum()) * grid.voxel_volume / volume - 1) < 0.05
    assert not np.array_equal(y[0], y[1]) and 0 <= x.min() and x.max() <= 1
    assert sorted(f.name.split("_")[1] for f in cache.glob("pair_*.npz")) == ["5000", "box-0", "box-1"]
    moved = tmp_path / "elsewhere" / "box.ply"
    moved.parent.mkdir()
    moved.write_bytes(box_file.read_bytes())
    build_pairs([0], cache=cache, noise_levels=(None,), mesh=moved, **SMALL)
    assert len(list(cache.glob("pair_*.npz"))) == 3  # the same bytes elsewhere: cached
    trimesh.creation.box(extents=(2.0, 1.0, 0.6)).export(moved)
    build_pairs([0], cache=cache, noise_levels=(None,), mesh=moved, **SMALL)
    assert len(list(cache.glob("pair_*.npz"))) == 4  # other bytes: made afresh
    with pytest.raises(ValueError, match="not both"):
        build_pairs([0], cache=cache, noise_levels=(None,), mesh=box_file, family="organic", **SMALL)


def test_second_stage_inputs_refine_the_first_stage_ones_and_are_cached(tmp_path, shared_pairs):
    """With ``refine`` each input is the first-stage one after a solve warm-started from it (so closer
    to its data), the truth is the same, and the refined inputs are cached by their options."""
    refine = {"iterations": 8, "coarse_to_fine": False, "lr": 0.05, "priors": {"tv": {"weight": 1e-3}}}
    x1, y1 = build_pairs([5000], cache=tmp_path, noise_levels=(None,), **SMALL)
    x2, y2 = build_pairs([5000], cache=tmp_path, noise_levels=(None,), refine=refine, **SMALL)
    assert np.array_equal(y1, y2) and not np.allclose(x1, x2) and 0 <= x2.min() and x2.max() <= 1
    assert 0 < np.abs(x2 - x1).mean() < 0.1  # a refinement of the first stage, not a new solve
    assert len(list(tmp_path.glob("pair_*.npz"))) == 1 and len(list(tmp_path.glob("stage2_*.npz"))) == 1
    again, _ = build_pairs([5000], cache=tmp_path, noise_levels=(None,), refine=refine, **SMALL)
    assert np.array_equal(again, x2)
    build_pairs([5000], cache=tmp_path, noise_levels=(None,), refine={**refine, "iterations": 9}, **SMALL)
    assert len(list(tmp_path.glob("stage2_*.npz"))) == 2  # other options: made afresh


def test_new_first_stage_weights_under_the_same_name_make_new_second_stage_inputs(tmp_path, shared_pairs, monkeypatch):
    """The second stage's round runs the learned prior, so its cache key holds the weights' bytes:
    a retrained first stage written over the same file is not handed the old round's inputs."""
    import dipnet.experiments.prior_pairs as prior_pairs

    rounds = []
    monkeypatch.setattr(prior_pairs, "refine_input", lambda seed, start, *_: rounds.append(seed) or start)
    weights = tmp_path / "first.pt"
    weights.write_bytes(b"first-stage weights, version 1")
    refine = {"iterations": 8, "priors": {"learned": {"weight": "auto", "weights": str(weights)}}}
    cache = tmp_path / "cache"
    for _ in range(2):
        build_pairs([5000], cache=cache, noise_levels=(None,), refine=refine, **SMALL)
    assert rounds == [5000]  # the second build reused the cached input
    weights.write_bytes(b"first-stage weights, version 2")
    build_pairs([5000], cache=cache, noise_levels=(None,), refine=refine, **SMALL)
    assert rounds == [5000, 5000] and len(list(cache.glob("stage2_*.npz"))) == 2
    assert refine_weights_digest({"iterations": 8}) is None  # no learned prior: no weights in the key
    assert refine_weights_digest({"priors": {"learned": {"weights": None}}}) == refine_weights_digest(
        {"priors": {"learned": {"weights": "denoiser64"}}})  # None is the shipped first stage
    with pytest.raises(PriorWeightsError, match="not found"):
        build_pairs([5000], cache=cache, noise_levels=(None,),
                    refine={"priors": {"learned": {"weights": str(tmp_path / "x.pt")}}}, **SMALL)


def test_noisy_options_change_only_the_noisy_pairs(tmp_path, shared_pairs):
    """``noisy_options`` reach the solver of the noisy pairs only: the noise-free pair is reused (its
    digest unchanged) and the noisy one is the solve with those options."""
    plain = build_pairs([5000], cache=tmp_path, noise_levels=(None, 30.0), **SMALL)
    options = {"noise_model": "correlated"}
    mixed = build_pairs([5000], cache=tmp_path, noise_levels=(None, 30.0), noisy_options=options, **SMALL)
    assert len(list(tmp_path.glob("pair_*.npz"))) == 3  # one new pair: the noisy one
    assert np.array_equal(plain[0][0], mixed[0][0]) and not np.array_equal(plain[0][1], mixed[0][1])
    x, _ = make_pair(5000, n=16, dips=8, snr_db=30.0, solver_options={**SMALL["solver_options"], **options})
    assert np.array_equal(mixed[0][1], x)


def test_a_tilt_limit_dips_the_pairs_along_the_rigs_plan_and_keys_them_apart(tmp_path, shared_pairs):
    """``max_tilt_deg`` below 90: the plan of a rig that tilts that far (no dip beyond it), pairs of their own;
    90 is the hemisphere's Fibonacci plan and its pairs' digest."""
    tilts = torch.rad2deg(torch.arccos(plan_directions(41, 35.0)[:, 2]))
    assert tilts.max() <= 35.0 + 1e-9 and tilts.min() >= 0.0
    assert torch.equal(plan_directions(41, 90.0), fibonacci_hemisphere(41))
    hemisphere = build_pairs([5000], cache=tmp_path, noise_levels=(None,), **SMALL)
    same = build_pairs([5000], cache=tmp_path, noise_levels=(None,), max_tilt_deg=90.0, **SMALL)
    tilted = build_pairs([5000], cache=tmp_path, noise_levels=(None,), max_tilt_deg=35.0, **SMALL)
    assert len(list(tmp_path.glob("pair_*.npz"))) == 2 and np.array_equal(hemisphere[0], same[0])
    assert np.array_equal(hemisphere[1], tilted[1]) and not np.array_equal(hemisphere[0], tilted[0])
    x, _ = make_pair(5000, n=16, dips=8, solver_options=SMALL["solver_options"], max_tilt_deg=35.0)
    assert np.array_equal(tilted[0][0], x)


@pytest.mark.slow
def test_worker_processes_make_the_same_pairs(tmp_path):
    one = build_pairs([5003, 5004], cache=tmp_path / "one", noise_levels=(None,), **SMALL)
    two = build_pairs([5003, 5004], cache=tmp_path / "two", noise_levels=(None,), workers=2, **SMALL)
    assert all(np.array_equal(a, b) for a, b in zip(one, two))


def test_a_damaged_cached_pair_is_made_again_with_a_warning(tmp_path, shared_pairs):
    """A pair file cut short (a build killed mid-write), emptied, or holding arrays of another size stopped the
    training with a traceback (``BadZipFile``, ``EOFError``) or ``error: all input arrays must have the same
    shape``; now each is named in a warning and made again, the same pair as before; no part file is left."""
    x, y = build_pairs([5000, 5001], cache=tmp_path, noise_levels=(None,), **SMALL)
    first, second = sorted(tmp_path.glob("pair_*.npz"))
    first.write_bytes(first.read_bytes()[:3000])
    np.savez_compressed(second, input=np.zeros((8, 8, 8), np.float32), target=np.zeros((8, 8, 8), np.float32))
    with pytest.warns(UserWarning) as caught:
        x2, y2 = build_pairs([5000, 5001], cache=tmp_path, noise_levels=(None,), **SMALL)
    messages = sorted(str(w.message) for w in caught if "cached training pair" in str(w.message))
    assert len(messages) == 2 and "its arrays have shapes (8, 8, 8) and (8, 8, 8), not (16, 16, 16)" in messages[1]
    assert "is not used (unreadable: " in messages[0] and messages[0].endswith("it is made again")
    assert np.array_equal(x, x2) and np.array_equal(y, y2)
    assert not list(tmp_path.glob("*.part*"))
