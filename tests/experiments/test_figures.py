"""A sweep's figures (dipnet.experiments.figures): metric curves against dips and noise, the montage, the volume
rendering."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.experiments import collect, figures

from sweep_fixtures import DIPS, SOLVERS, ball, is_png, write_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return write_sweep(tmp_path_factory.mktemp("sweep"))


def test_plots(sweep, tmp_path):
    runs = collect.collect_runs(sweep)
    rows = collect.run_rows(runs)
    assert is_png(figures.plot_vs_dips(collect.aggregate(rows, ("solver", "n_dips")), tmp_path / "d.png"))
    assert is_png(figures.plot_vs_dips(collect.aggregate(rows, ("solver", "dips_percent")),
                                            tmp_path / "p.png", x="dips_percent"))
    assert is_png(figures.plot_vs_snr(collect.aggregate(rows, ("solver", "snr_db")), tmp_path / "s.png"))
    with pytest.raises(ValueError, match="snr_db"):
        figures.plot_vs_snr(collect.aggregate(rows[:2], ("solver", "snr_db")), tmp_path / "x.png")
    with pytest.raises(ValueError, match="metrics"):
        figures.plot_vs_dips(collect.aggregate(rows, ("solver", "n_dips"), metrics=()), tmp_path / "y.png")
    cells = figures.pick_montage(runs)
    assert set(cells) == {(s, n) for s in SOLVERS for n in DIPS}
    # the noise-free, lowest-seed run represents each cell
    assert all(c.metrics["snr_db"] is None and c.config["seed"] == 0 for c in cells.values())
    assert is_png(figures.plot_montage(runs, tmp_path / "m.png"))
    rows_of = {k[0] for k in figures.pick_montage(runs, ("shape", "solver"))}
    assert rows_of == {f"disk / {s}" for s in SOLVERS}
    assert figures.varying(rows) == ["solver"]                    # one shape: rows by solver
    with pytest.raises(ValueError, match="no finished run"):
        figures.plot_montage(runs[-3:], tmp_path / "none.png")


def test_render_volume_shows_the_front_of_a_ball():
    grid = Grid(24, 3, 100.0)
    vol = ball(grid, 30.0)
    image = figures.render_volume(vol)
    assert image.shape == (24, 24)
    silhouette = vol.any(axis=1)[::-1]                                # seen along y, z up
    np.testing.assert_array_equal(image > 0, silhouette)
    centre = image[10:14, 10:14].mean()
    yy, xx = np.mgrid[:24, :24] - 11.5
    rim = image[(image > 0) & (np.hypot(yy, xx) > 5)].mean()
    assert centre > rim                                               # nearer (and facing) = brighter
    image2d = figures.render_volume(vol[12])
    np.testing.assert_array_equal(image2d, vol[12][::-1].astype(float))
