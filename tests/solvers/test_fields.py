"""Neural occupancy fields (dipnet.solvers.fields): the three coordinate encodings (sizes, known values,
interpolation), option errors, exact built-in symmetry, the output bias."""

from __future__ import annotations

import math

import pytest
import torch

from dipnet.solvers.fields import DenseGridEncoding, FourierFeatures, OccupancyField, PositionalEncoding, make_encoding
from dipnet.solvers.priors import symmetry_maps


@pytest.mark.parametrize("ndim,symmetry", [
    (2, {"plane_normal": [1.0, 0.0]}), (2, {"order": 3}),
    (3, {"plane_normal": [0.0, 1.0, 1.0]}), (3, {"axis": [0.0, 0.0, 1.0], "order": 5}),
    (3, {"plane_normal": [1.0, 0.0, 0.0], "axis": [0.0, 0.0, 1.0], "order": 4}),
])
def test_built_in_symmetry_is_exact(ndim, symmetry):
    torch.manual_seed(0)
    field = OccupancyField(ndim, {"type": "fourier", "n_features": 16, "scale": 2.0}, 16, 1, symmetry)
    pts = torch.rand(200, ndim) * 1.6 - 0.8
    maps = symmetry_maps(ndim, symmetry.get("plane_normal"), symmetry.get("axis"), symmetry.get("order", 1))
    with torch.no_grad():
        base = field(pts)
        for m in maps:
            torch.testing.assert_close(field(pts @ m.T.float()), base, atol=1e-5, rtol=1e-5)
        assert base.std() > 0  # and not trivially constant


def test_densegrid_interpolates_its_grid():
    enc = make_encoding(2, {"type": "densegrid", "levels": 1, "features": 1, "base_resolution": 4,
                            "max_resolution": 4})
    with torch.no_grad():
        enc.grids[0].copy_(torch.arange(16.0).reshape(1, 1, 4, 4))  # value 4 * row + column
    centres = torch.tensor([[-0.75, -0.75], [0.75, -0.75], [-0.75, 0.75], [0.0, 0.0]])  # cell centres (x, y)
    torch.testing.assert_close(enc(centres)[:, 0], torch.tensor([0.0, 3.0, 12.0, 7.5]))


def test_fourier_features_are_sines_and_cosines_of_the_projections():
    torch.manual_seed(0)
    enc = FourierFeatures(3, n_features=8, scale=2.0)
    x = torch.rand(50, 3) * 2 - 1
    out = enc(x)
    assert enc.out_dim == 2 * 8 + 3 == out.shape[1]
    proj = 2 * math.pi * x @ enc.freqs
    torch.testing.assert_close(out, torch.cat([torch.sin(proj), torch.cos(proj), x], dim=1))
    torch.testing.assert_close(out[:, :8] ** 2 + out[:, 8:16] ** 2, torch.ones(50, 8))
    assert FourierFeatures(2, n_features=4, include_input=False).out_dim == 8


def test_positional_encoding_is_the_octave_ladder():
    enc = PositionalEncoding(2, n_frequencies=3)
    x = torch.tensor([[0.5, -0.25]])
    out = enc(x)
    assert out.shape == (1, enc.out_dim) == (1, 2 * (1 + 2 * 3))
    angles = torch.tensor([0.5, 1.0, 2.0, -0.25, -0.5, -1.0]) * math.pi  # per axis: 2^k pi x, k = 0, 1, 2
    torch.testing.assert_close(out[0], torch.cat([x[0], torch.sin(angles), torch.cos(angles)]))


def test_densegrid_resolutions_grow_geometrically():
    enc = DenseGridEncoding(3, levels=4, features=2, base_resolution=4, max_resolution=32)
    assert enc.resolutions == [4, 8, 16, 32] and enc.out_dim == 8
    assert [tuple(g.shape) for g in enc.grids] == [(1, 2, r, r, r) for r in (4, 8, 16, 32)]
    assert enc(torch.zeros(5, 3)).shape == (5, 8)


@pytest.mark.parametrize("spec,message", [
    ({"type": "hash"}, "unknown field encoding 'hash'"),
    ({"type": "positional", "octaves": 3}, "bad options for encoding 'positional'"),
    ({"type": "densegrid", "base_resolution": 8, "max_resolution": 4},
     "base_resolution <= max_resolution .*got base_resolution 8 and max_resolution 4"),
])
def test_bad_encodings_are_named(spec, message):
    with pytest.raises(ValueError, match=message):
        make_encoding(3, spec)


def test_the_default_encoding_is_the_dense_grid():
    assert isinstance(make_encoding(2, None), DenseGridEncoding)


def test_the_output_bias_starts_a_uniform_field_and_bad_symmetries_are_named():
    field = OccupancyField(3, {"type": "positional", "n_frequencies": 2}, hidden_width=8, hidden_layers=1)
    with torch.no_grad():
        field.head.weight.zero_()
        field.set_output_bias(math.log(0.3 / 0.7))
        occupancy = torch.sigmoid(field(torch.rand(20, 3) * 2 - 1))
    torch.testing.assert_close(occupancy, torch.full((20,), 0.3))
    with pytest.raises(ValueError, match="unknown symmetry options"):
        OccupancyField(3, symmetry={"mirror": [1, 0, 0]})


@pytest.mark.parametrize("options, message", [({"scale": math.nan}, "scale must be a finite number > 0"),
                                              ({"scale": 0.0}, "scale must be a finite number > 0"),
                                              ({"include_input": "no"}, "include_input must be true or false")])
def test_fourier_encoding_options_are_checked(options, message):
    """A NaN scale was a NaN loss named a divergence ("try a lower lr"); ``include_input: no`` was read as true."""
    with pytest.raises(ValueError, match=message):
        make_encoding(3, {"type": "fourier", **options})


@pytest.mark.parametrize("spec, message", [
    ({"type": "fourier", "n_features": 2.5}, r"fourier encoding's n_features must be a whole number, got 2.5"),
    ({"type": "fourier", "n_features": True}, r"fourier encoding's n_features must be a whole number, got True"),
    ({"type": "fourier", "n_features": "8"}, r"fourier encoding's n_features must be a whole number, got '8'"),
    ({"type": "fourier", "n_features": 0}, r"fourier encoding's n_features must be a whole number >= 1, got 0"),
    ({"type": "fourier", "n_features": -3}, r"fourier encoding's n_features must be a whole number >= 1, got -3"),
    ({"type": "positional", "n_frequencies": 2.5}, r"positional encoding's n_frequencies must be a whole number"),
    ({"type": "positional", "n_frequencies": "6"}, r"positional encoding's n_frequencies must be a whole number"),
    ({"type": "positional", "n_frequencies": -1}, r"positional encoding's n_frequencies must be a whole number >= 0"),
    ({"type": "densegrid", "levels": 2.5}, r"densegrid encoding's levels must be a whole number, got 2.5"),
    ({"type": "densegrid", "features": True}, r"densegrid encoding's features must be a whole number, got True"),
    ({"type": "densegrid", "max_resolution": 8.5}, r"densegrid encoding's max_resolution must be a whole number"),
    ({"type": "densegrid", "init_scale": -1.0}, r"densegrid encoding's init_scale must be a finite number > 0"),
])
def test_encoding_counts_are_whole_numbers(spec, message):
    """``n_features: 2.5`` (or ``true``, ``"8"``) was cut or parsed to a count without a word, ``n_frequencies: 2.5`` as
    well, and a negative one was torch's "negative dimension" / "bound inconsistent with step sign" naming no
    option."""
    with pytest.raises(ValueError, match=message):
        make_encoding(3, spec)
    assert make_encoding(2, {"type": "positional", "n_frequencies": 0}).out_dim == 2  # the coordinates alone
