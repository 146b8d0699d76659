"""The sweep montage shows what differs between jobs: the overrides that differ label the cells,
the cells are cut open, and the voxels that differ from the best cell are marked and counted."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dipnet.core.grid import Grid
from dipnet.experiments import collect, figures
from dipnet.experiments.collect import Run
from sweep_fixtures import ball, write_job


def test_only_the_overrides_that_differ_label_a_job():
    runs = [Run(Path(str(i)), "ok", overrides=o) for i, o in enumerate((
        ["solver=minnorm", "n_dips=20", "seed=0"], ["solver=lsmr", "n_dips=20", "seed=0"], ["solver=lsmr", "n_dips=60",
                                                                                           "seed=0"]))]
    assert list(figures.differing_overrides(runs).values()) == [
        "n_dips=20 solver=minnorm", "n_dips=20 solver=lsmr", "n_dips=60 solver=lsmr"]
    same = [Run(Path("a"), "ok", overrides=["seed=0"]), Run(Path("b"), "ok", overrides=["seed=0"])]
    assert set(figures.differing_overrides(same).values()) == {"(same overrides)"}


def test_a_cut_view_shows_a_hollow_ball_and_its_section():
    grid = Grid(24, 3, 100.0)
    hollow = ball(grid, 40.0) & ~ball(grid, 20.0)
    whole, cut = figures.render_volume(hollow), figures.render_volume(hollow, cut=True)
    assert (whole[10:14, 10:14] > 0).all()                            # from outside: the shell's front
    section = figures.mid_section(hollow)
    np.testing.assert_array_equal(section, hollow[:, 12, :][::-1])
    inner = ~section & (cut > 0)                                      # the hole of the section shows the back wall
    assert inner[10:14, 10:14].all() and cut[inner].max() < np.median(cut[section])   # farther = fainter


def test_the_montage_titles_and_marks_the_differences(tmp_path, monkeypatch):
    for i, n in enumerate((4, 8, 16)):
        write_job(tmp_path / str(i), solver="minnorm", n_dips=n, snr_db=None, seed=0, ndim=3, resolution=16,
                  metrics={"iou": 1 - 1 / n})
    figs = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: figs.append(fig) or path)
    figures.plot_montage(collect.collect_runs(tmp_path), tmp_path / "m.png")
    titles = [ax.get_title() for ax in figs[0].axes]
    volumes = {n: np.load(tmp_path / str(i) / "reconstruction.npz")["binary"] for i, n in enumerate((4, 8, 16))}
    differ = int((volumes[4] != volumes[16]).sum())
    assert titles[0] == f"n_dips=4\nIoU 0.750 · {differ} voxels differ"
    assert titles[2] == "n_dips=16\nIoU 0.938 · reference"          # the best IoU is the reference
    assert len(figs[0].axes[0].images) == 2 and len(figs[0].axes[2].images) == 1   # differences drawn over cell 0


def test_a_null_iou_of_strict_json_is_no_reference(tmp_path, monkeypatch):
    for i, (n, iou) in enumerate(((4, None), (8, 0.8))):
        write_job(tmp_path / str(i), solver="minnorm", n_dips=n, snr_db=None, seed=0, ndim=3, resolution=16,
                  metrics={"iou": iou})
    figs = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: figs.append(fig) or path)
    figures.plot_montage(collect.collect_runs(tmp_path), tmp_path / "m.png")
    assert figs[0].axes[1].get_title().endswith("\nIoU 0.800 · reference")


def test_a_sweep_over_resolution_draws_its_montage(tmp_path, monkeypatch):
    """Before: ``compare.py`` on jobs of 12^3 and 24^3 (``resolution=12,24``; or 2D beside 3D) printed
    "skipping montage.png: setting an array element with a sequence. The requested array has an inhomogeneous
    shape ..." (one zoom box from all the pictures) and drew none. Now each picture size has its own zoom."""
    for i, n in enumerate((12, 24)):
        write_job(tmp_path / str(i), solver="minnorm", n_dips=8, snr_db=None, seed=0, ndim=3, resolution=n,
                  metrics={"iou": 0.5 + i / 4})
    figs = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: figs.append(fig) or path)
    figures.plot_montage(collect.collect_runs(tmp_path), tmp_path / "m.png", row_key="resolution")
    shown = [ax for ax in figs[0].axes if ax.images]
    assert len(shown) == 2
    for ax in shown:  # every cell zoomed inside its own picture
        (x0, x1), width = ax.get_xlim(), ax.images[0].get_array().shape[1]
        assert -0.5 <= x0 < x1 <= width - 0.5
