"""Every figure function writes a readable, non-trivial PNG."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch
import trimesh

from dipnet.core.grid import Grid
from dipnet.outputs import plots
from dipnet.outputs.plots import cut_away, plot_history, plot_mesh, plot_profiles, plot_sinogram, plot_slices
from dipnet.shapes import builtin_shape
from dipnet.shapes.isosurface import volume_to_mesh


def check_png(path) -> None:
    assert path.suffix == ".png" and path.stat().st_size > 5_000
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert img[..., :3].std() > 0.01  # not a blank canvas


def ball(grid: Grid, radius: float) -> np.ndarray:
    return (np.linalg.norm(grid.centers().numpy(), axis=-1) < radius).astype(np.float32)


def test_sinogram_2d_and_3d(tmp_path):
    rng = np.random.default_rng(0)
    check_png(plot_sinogram(rng.random((20, 32)), tmp_path / "s2.png", angles_deg=np.arange(20) * 9.0,
                            slab_edges=np.linspace(-50, 50, 33)))
    check_png(plot_sinogram(torch.rand(50, 24, generator=torch.Generator().manual_seed(0)), tmp_path / "s3.png"))
    with pytest.raises(ValueError, match="shape"):
        plot_sinogram(np.zeros(5), tmp_path / "bad.png")


@pytest.mark.parametrize("ndim", [2, 3])
def test_slices(tmp_path, ndim):
    grid = Grid(24, ndim=ndim)
    truth = ball(grid, 30.0)
    recon = truth + 0.1 * np.random.default_rng(1).normal(size=truth.shape)
    check_png(plot_slices(truth, torch.from_numpy(recon), tmp_path / "sub" / "slices.png"))
    with pytest.raises(ValueError, match="one shape"):
        plot_slices(truth, truth[:-1], tmp_path / "bad.png")


def test_mesh_single_list_decimated_and_empty(tmp_path):
    grid = Grid(32)
    mesh = volume_to_mesh(ball(grid, 35.0), grid)
    assert len(mesh.faces) > 1000
    check_png(plot_mesh(mesh, tmp_path / "one.png"))
    check_png(plot_mesh([mesh, trimesh.creation.torus(20, 8), trimesh.Trimesh()], tmp_path / "three.png",
                        titles=["ball", "torus", "empty"], max_faces=500))
    with pytest.raises(ValueError, match="titles"):
        plot_mesh([mesh], tmp_path / "bad.png", titles=["a", "b"])


def test_history(tmp_path):
    steps = np.arange(1, 101)
    check_png(plot_history({"data": list(1.0 / steps), "prior": list(0.1 / np.sqrt(steps))}, tmp_path / "h.png"))
    check_png(plot_history({"signed": list(np.sin(steps / 10.0))}, tmp_path / "h2.png"))


def test_profiles(tmp_path):
    x = np.linspace(-1, 1, 40)
    meas = np.stack([np.clip(1 - (x - 0.1 * k) ** 2, 0, None) for k in range(8)])
    check_png(plot_profiles(meas, meas * 1.05, tmp_path / "p.png", k=3, slab_edges=torch.linspace(-50, 50, 41)))
    check_png(plot_profiles(torch.from_numpy(meas), None, tmp_path / "p2.png", k=[0, 7]))


def test_mesh_figure_has_a_cutaway_row_that_shows_an_inner_chamber(tmp_path):
    grid = Grid(24, 3, 110.0)
    shape = builtin_shape("chamber_box", 3, 45.0)
    mesh = volume_to_mesh(shape.occupancy(grid).numpy(), grid, 0.5)
    cut = cut_away(mesh)
    used = cut.vertices[np.unique(cut.faces)]
    assert 0 < len(cut.faces) < len(mesh.faces) and used[:, 1].min() >= 0
    chamber = shape.chamber[1][0]  # chamber half size (mm): its walls lie well inside the box
    inner = np.abs(used[:, [0, 2]]).max(axis=1) < 0.5 * (chamber + shape.hi[0])
    assert inner.sum() > 10  # the cut exposes the chamber walls
    for name, cutaway in (("cut.png", True), ("flat.png", False)):
        check_png(plot_mesh([mesh, mesh], tmp_path / name, titles=["truth", "recon"], cutaway=cutaway))
    rows = mpimg.imread(tmp_path / "cut.png").shape[0] / mpimg.imread(tmp_path / "flat.png").shape[0]
    assert rows > 1.8  # a second row of panels


def _captured(monkeypatch):
    figs = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: figs.append(fig) or path)
    return figs


def test_slices_have_mm_axes_positions_and_a_counted_missed_extra_legend(monkeypatch, tmp_path):
    figs = _captured(monkeypatch)
    grid = Grid(16, 3, 80.0)                                          # voxel 5 mm, centres at -37.5 ... 37.5
    truth = np.zeros(grid.shape)
    truth[4:12, 4:12, 4:12] = 1.0
    recon = truth.copy()
    recon[8, 5, 6] = 0.0                                              # missed in the z = mid cut
    recon[8, 2, 6] = recon[8, 2, 7] = 1.0                             # two extra there
    plots.plot_slices(truth, recon, tmp_path / "s.png", extent_mm=grid.extent)
    (fig,) = figs
    axes = fig.axes
    assert axes[0].get_title() == "truth: z = 2.5 mm"                 # voxel 8: -40 + 8.5 * 5
    assert axes[0].get_xlabel() == "x (mm)" and axes[4].get_ylabel() == "z (mm)" and axes[7].get_xlabel() == "y (mm)"
    assert axes[0].get_xlim()[1] <= 40.0
    legend = [t.get_text() for t in axes[2].get_legend().get_texts()]
    assert legend == ["missed (1)", "extra (2)"]
    assert [t.get_text() for t in axes[5].get_legend().get_texts()] == ["missed (0)", "extra (0)"]  # y = mid cut
    assert "missed: in the truth, not reconstructed" in fig._suptitle.get_text()
