"""Figures and pages that answer: slices in mm with a labelled missed/extra legend, a report under 1 MB that
loads one shared plotly file and opens with the three answers."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.outputs import plots

from sweep_fixtures import METRICS, write_job


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


@pytest.fixture()
def sweep(tmp_path):
    (tmp_path / "multirun.yaml").write_text("hydra: {}\n")
    for i, n in enumerate((10, 40)):
        job = write_job(tmp_path / str(i), solver="minnorm", n_dips=n, snr_db=None, seed=0, ndim=3, resolution=40,
                        metrics=METRICS)
        for name in ("slices.png", "uncertainty.png", "resolvability.png"):
            (job / name).write_bytes(b"\x89PNG fake")
    return tmp_path


def test_run_pages_share_one_plotly_file_and_stay_under_a_megabyte(sweep):
    from dipnet.outputs import report

    pages = [report.write_run_report(sweep / str(i)) for i in (0, 1)]
    assert sorted(p.name for p in sweep.rglob("plotly.min.js")) == ["plotly.min.js"]    # one, in the sweep dir
    assert (sweep / "plotly.min.js").stat().st_size > 1_000_000
    for page in pages:
        text = page.read_text()
        assert page.stat().st_size < 1_000_000
        assert re.findall(r"<script src='([^']+)'", text) == ["../plotly.min.js"]
        assert "Plotly.newPlot" in text and len(re.findall(r"<script[^>]*>", text)) == 1 + text.count("Plotly.newPlot")
        for name in ("slices.png", "uncertainty.png", "resolvability.png"):
            assert f'src="{name}"' in text                             # linked, not inlined
        # the page opens with the view and the three answers; the grouped table comes after them
        assert text.index('id="meshes"') < text.index("How close to the truth?") < text.index("How sure?") \
            < text.index("every metric") < text.index("how consistent with the data</h3>")


def test_the_3d_view_is_cut_open_with_a_button_for_the_whole(sweep):
    from dipnet.outputs import report

    text = report.write_run_report(sweep / "0").read_text()
    spec = json.loads(re.search(r'Plotly.newPlot\(\s*"meshes",\s*(\[.*?\]),\s*(\{.*?\})\s*,\s*\{"responsive"',
                                text, re.S).group(1))
    assert [(t["name"], t.get("visible", True)) for t in spec] == [
        ("truth", True), ("truth", False), ("reconstruction", True), ("reconstruction", False)]
    assert "cut open at y = 0 mm" in text and ">whole<" not in text and '"label":"whole"' in text.replace(" ", "")
