"""Figures and pages that answer: slices in mm with a labelled missed/extra legend, the three
first answers, a report under 1 MB that loads one shared plotly file, warnings shown once."""

from __future__ import annotations

import json
import logging
import re
import warnings

import numpy as np
import pytest

from dipnet.core.grid import Grid
from dipnet.jobs import warnings_once
from dipnet.outputs import plots, summary
from sweep_fixtures import write_job

METRICS = {"iou": 0.9687, "chamfer": 0.004018, "profile_residual": 0.0588, "profile_residual_expected": 0.0226,
           "volume_ratio": 1.059, "consistency": "inconsistent", "uncertain_fraction": 0.2624,
           "expected_error_fraction": 0.3087, "seconds": 12.05, "validation": {"readings_repaired": 0},
           "error_rate_by_uncertainty_decile": [0.0] * 9 + [0.24], "some_new_metric": 1.5}


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


def test_the_three_answers_and_a_short_headline():
    found = {a.question: a for a in summary.answers(METRICS)}
    assert found["How close to the truth?"].headline == "IoU 0.969"
    assert "0.40%" in found["How close to the truth?"].detail
    assert found["How consistent with its data?"].headline == "residual 5.9% (noise 2.3%)"
    assert "1.059" in found["How consistent with its data?"].detail
    assert found["How sure?"].headline == "26% uncertain"
    assert [a.question for a in summary.answers({"profile_residual": 0.1})] == ["How consistent with its data?"]
    line = summary.headline(METRICS)
    assert len(line) < 160 and "IoU 0.969" in line and "inconsistent" in line


def test_every_metric_is_grouped_once_with_a_label():
    groups = summary.grouped(METRICS)
    keys = [key for rows in groups.values() for _, key, _ in rows]
    assert sorted(keys) == sorted(METRICS)
    assert list(groups)[0] == "how close to the truth" and ("some new metric", "some_new_metric", 1.5) in groups["other"]


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
    from dipnet.experiments import report

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
    from dipnet.experiments import report

    text = report.write_run_report(sweep / "0").read_text()
    spec = json.loads(re.search(r'Plotly.newPlot\(\s*"meshes",\s*(\[.*?\]),\s*(\{.*?\})\s*,\s*\{"responsive"',
                                text, re.S).group(1))
    assert [(t["name"], t.get("visible", True)) for t in spec] == [
        ("truth", True), ("truth", False), ("reconstruction", True), ("reconstruction", False)]
    assert "cut open at y = 0 mm" in text and ">whole<" not in text and '"label":"whole"' in text.replace(" ", "")


def test_a_warning_that_was_logged_is_shown_once(monkeypatch, capfd):
    monkeypatch.setattr(warnings_once, "_installed", False)
    monkeypatch.setattr(warnings_once, "_logged", set())
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    factory = logging.getLogRecordFactory()
    log = logging.getLogger("dipnet.test_answers")
    handler = logging.StreamHandler()                                 # stderr, as Hydra's console handler
    for name in ("dipnet.test_answers", warnings_once.WARNINGS_LOGGER):
        logging.getLogger(name).addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings_once.log_warnings_once()
            log.warning("the reconstruction holds too much")
            warnings.warn("the reconstruction holds too much", UserWarning)   # the same finding: not again
            warnings.warn("only warned, never logged", UserWarning)           # shown once, through logging
            with pytest.raises(UserWarning):                                  # filters still come first
                warnings.simplefilter("error")
                warnings.warn("an error now", UserWarning)
    finally:
        logging.setLogRecordFactory(factory)
        for name in ("dipnet.test_answers", warnings_once.WARNINGS_LOGGER):
            logging.getLogger(name).removeHandler(handler)
    err = capfd.readouterr().err
    assert err.count("the reconstruction holds too much") == 1
    assert err.count("only warned, never logged") == 1 and "UserWarning: only warned" in err
