"""The denoiser network and its weights file: shapes, identity at start, round trip, named errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from dipnet.solvers.denoiser import (
    SHIPPED_DIR,
    SHIPPED_WEIGHTS,
    OccupancyDenoiser,
    PriorWeightsError,
    load_weights,
    save_weights,
    shipped_names,
    weights_path,
)

from solver_helpers import perturbed_denoiser

META = {"n": 16, "ndim": 3, "n_slabs_per_voxel": 1}


def test_untrained_denoiser_is_the_identity_and_keeps_the_shape():
    torch.manual_seed(0)
    net = OccupancyDenoiser(channels=2)
    x = torch.rand(2, 1, 16, 16, 16)
    assert torch.equal(net(x), x)
    with pytest.raises(ValueError, match="divisible by 4"):
        net(torch.rand(1, 1, 10, 10, 10))


def test_weights_round_trip(tmp_path):
    net = perturbed_denoiser(0.1, seed=1)
    path = save_weights(net, tmp_path / "w.pt", {**META, "seed": 3})
    loaded, meta = load_weights(path)
    assert meta["seed"] == 3 and meta["channels"] == 2 and (tmp_path / "w.json").is_file()
    x = torch.rand(1, 1, 16, 16, 16)
    with torch.no_grad():
        assert torch.allclose(loaded(x), net(x))
        assert not torch.equal(loaded(x), x)


def test_missing_corrupt_and_foreign_files_get_one_named_error(tmp_path):
    with pytest.raises(PriorWeightsError, match="not found"):
        load_weights(tmp_path / "nothing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(PriorWeightsError, match=r"bad\.pt are not a dipnet denoiser weights file") as err:
        load_weights(bad)
    assert "weights_only" not in str(err.value)  # torch's advice to load a foreign file unsafely is not passed on
    cut = tmp_path / "cut.pt"
    cut.write_bytes(save_weights(OccupancyDenoiser(2), tmp_path / "whole.pt", META).read_bytes()[:500])
    with pytest.raises(PriorWeightsError, match="unreadable"):
        load_weights(cut)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(PriorWeightsError, match="not a dipnet denoiser"):
        load_weights(foreign)
    good = save_weights(OccupancyDenoiser(2), tmp_path / "good.pt", META)
    saved = torch.load(good, weights_only=True)
    saved["meta"]["channels"] = 4  # meta that does not fit the tensors
    torch.save(saved, good)
    with pytest.raises(PriorWeightsError, match="do not fit"):
        load_weights(good)


def test_weights_holding_nan_or_inf_are_refused_naming_the_file_and_tensor(tmp_path):
    """Weights that load but hold a NaN (a diverged training) would make every solve's loss NaN: refused at load."""
    net = OccupancyDenoiser(2)
    with torch.no_grad():
        net.up0[0].bias[1] = float("nan")
        net.out.weight.fill_(float("inf"))
    path = save_weights(net, tmp_path / "nan.pt", META)
    with pytest.raises(PriorWeightsError, match=r"weights .*nan\.pt: tensor up0\.0\.bias holds NaN or infinite "
                                                r"values \(and 1 more\).*lower --lr"):
        load_weights(path)


def test_shipped_weights_load_without_network():
    model, meta = load_weights(None)
    assert SHIPPED_WEIGHTS.is_file() and SHIPPED_WEIGHTS.stat().st_size < 20e6
    assert meta["n"] == 64 and meta["ndim"] == 3 and "config" in meta and "seed" in meta["config"]
    assert SHIPPED_WEIGHTS.with_suffix(".json").is_file()


def test_weights_are_a_path_or_the_name_of_shipped_ones(tmp_path):
    assert weights_path(None) == SHIPPED_WEIGHTS == weights_path("denoiser64")
    assert weights_path("denoiser64_stage2") == SHIPPED_DIR / "denoiser64_stage2.pt"
    assert weights_path(tmp_path / "w.pt") == tmp_path / "w.pt" and weights_path("w.pt").name == "w.pt"
    assert weights_path("sub/name") == Path("sub/name")  # a folder makes it a path
    with pytest.raises(PriorWeightsError, match="denoiser64_stage2"):  # the error lists the shipped names
        load_weights("no_such_weights")


def test_the_shipped_second_stage_is_the_first_fine_tuned_on_its_rounds():
    assert shipped_names() == ["denoiser64", "denoiser64_stage2", "denoiser64_tilt35"]
    first, _ = load_weights(None)
    second, meta = load_weights("denoiser64_stage2")
    assert (SHIPPED_DIR / "denoiser64_stage2.pt").stat().st_size < 20e6
    assert (SHIPPED_DIR / "denoiser64_stage2.json").is_file()
    config = meta["config"]
    assert config["init_weights"] == "denoiser64" and config["refine"]["rounds"] == 1
    assert config["refine"]["priors"]["learned"]["weights"] is None  # its inputs: a round anchored to the first
    assert meta["n"] == 64 and meta["validation"][1] < meta["validation"][2]  # it improves its own inputs
    x = torch.rand(1, 1, 64, 64, 64)
    with torch.no_grad():
        assert not torch.allclose(first(x), second(x), atol=1e-4)


def test_the_shipped_weights_for_a_rig_that_tilts_0_to_35_deg_say_so():
    """``denoiser64_tilt35``: the first stage's recipe on pairs dipped along a 0-35 deg plan; its plan warning is
    silent for that rig's dips and speaks for the hemisphere's (a band 10 deg narrower or more is not warned)."""
    from dipnet.core.orientations import Reach, fibonacci_hemisphere
    from dipnet.solvers.learned import LearnedPrior

    model, meta = load_weights("denoiser64_tilt35")
    assert (SHIPPED_DIR / "denoiser64_tilt35.pt").stat().st_size < 20e6
    config = meta["config"]
    assert config["max_tilt_deg"] == 35.0 and config["dips"] == 41 and config["init_weights"] is None
    assert meta["n"] == 64 and meta["validation"][1] < meta["validation"][2]
    prior = LearnedPrior("denoiser64_tilt35")
    assert prior.plan_warning(Reach(tilt_range_deg=(0.0, 35.0)).uniform(41)) is None
    assert prior.plan_warning(fibonacci_hemisphere(41)) is None
    assert "tilted 0-35 deg" in prior.plan_warning(Reach(tilt_range_deg=(0.0, 15.0)).uniform(41))


def test_weights_meta_without_its_grid_names_the_file(tmp_path):
    path = save_weights(OccupancyDenoiser(2), tmp_path / "no_n.pt", META)
    saved = torch.load(path, weights_only=True)
    del saved["meta"]["n"]
    torch.save(saved, path)
    with pytest.raises(PriorWeightsError, match=r"learned-prior weights .*no_n\.pt: their meta lacks n \("):
        load_weights(path)


@pytest.mark.parametrize("key, value", [("n", "abc"), ("n", 30), ("n", 0), ("ndim", 4),
                                        ("n_slabs_per_voxel", float("nan")), ("n_slabs_per_voxel", -1),
                                        ("channels", 2.5)])
def test_weights_meta_with_an_impossible_grid_names_the_key(tmp_path, key, value):
    """A meta value no weights file can hold (a U-Net grid that is not a positive multiple of 4, a NaN slab
    spacing, which passed the slab check as no mismatch) is one named error when the file is read."""
    path = save_weights(OccupancyDenoiser(2), tmp_path / "edited.pt", META)
    saved = torch.load(path, weights_only=True)
    saved["meta"][key] = value
    torch.save(saved, path)
    with pytest.raises(PriorWeightsError, match=rf"edited\.pt: their meta gives {key}="):
        load_weights(path)


def test_a_folder_given_as_weights_is_named_a_folder(tmp_path):
    """``weights=<a folder>`` (the folder of a training run, the .pt left off) said "weights not found: <folder>",
    though the folder is there; now it says it is a folder and names the weights files in it."""
    save_weights(OccupancyDenoiser(2), tmp_path / "run" / "d.pt", META)
    with pytest.raises(PriorWeightsError, match=r"weights .*run is a folder, not a weights file: give the \.pt file "
                                                r"in it \(d\.pt\)"):
        load_weights(tmp_path / "run")
    with pytest.raises(PriorWeightsError, match=r"is a folder, not a weights file: .*\(it holds no \.pt file\)"):
        load_weights(tmp_path)
