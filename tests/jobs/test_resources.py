"""Memory estimates from the config alone: the dominant terms, and refusal before any allocation."""

import pytest
from hydra import compose, initialize_config_module

from dipnet.core.memory import ResourceError
from dipnet.jobs.resources import check_memory, estimate_memory


def _cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_the_grid_terms_grow_with_the_voxels():
    small, large = estimate_memory(_cfg("resolution=40")), estimate_memory(_cfg("resolution=80"))
    assert large.parts["grid"] / small.parts["grid"] == pytest.approx(8.0)
    assert large.parts["truth"] / small.parts["truth"] == pytest.approx(8.0)


def test_a_recorded_source_allocates_no_truth():
    recorded = estimate_memory(_cfg("source=recorded", "source.reader.path=x.npz"))
    assert "truth" not in recorded.parts and "truth" in estimate_memory(_cfg()).parts


def test_minnorm_with_cholesky_holds_the_dense_gram_matrix():
    k, n = 120, 40  # K dips of M = N slabs: B B^T is (K M)^2 doubles
    parts = estimate_memory(_cfg(f"n_dips={k}", f"resolution={n}")).parts
    assert parts["solver"] >= 8.0 * (k * n) ** 2


def test_a_run_beyond_the_memory_is_refused_with_both_figures():
    cfg = _cfg("resolution=40")
    assert check_memory(cfg, available=10**15).total > 0
    with pytest.raises(ResourceError, match=r"resolution=40 .* needs ~.* this machine has 1 KB available"):
        check_memory(cfg, available=1000)
