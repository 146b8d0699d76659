"""HTML reports (dipnet.experiments.report): the pages hold the run's pieces, a run page stays under 1 MB with one
shared plotly file, opens with the three answers and a cut-open 3D view, and headless Chromium renders the meshes
in WebGL without console errors, plotly loaded from the shared file (skipped without plotly or chromium)."""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import plotly  # noqa: F401  (the `report` extra, installed by the README test command)
import pytest

from dipnet.experiments import collect, report

from sweep_fixtures import METRICS, write_job

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

#: Injected at the top of a copy of the page: records console errors, uncaught exceptions and
#: rejected promises, then (after load) what every plotly graph holds, into <pre id="probe">.
PROBE = """<script>
window.__errors = [];
(function () {
  const error = console.error;
  console.error = function (...args) { window.__errors.push(args.map(String).join(' ')); error.apply(console, args); };
  window.addEventListener('error', e => window.__errors.push('uncaught: ' + e.message));
  window.addEventListener('unhandledrejection', e => window.__errors.push('rejection: ' + e.reason));
  window.addEventListener('load', () => setTimeout(() => {
    const plots = [...document.querySelectorAll('.js-plotly-plot')].map(gd => ({
      id: gd.id,
      traces: (gd._fullData || []).map(t => ({type: t.type, name: t.name, faces: t.i ? t.i.length : 0})),
      canvases: gd.querySelectorAll('.gl-container canvas').length}));
    const pre = document.createElement('pre');
    pre.id = 'probe';
    pre.textContent = JSON.stringify({errors: window.__errors, plots: plots});
    document.body.appendChild(pre);
  }, 1000));
})();
</script>"""


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sweep")
    (root / "multirun.yaml").write_text("hydra: {}\n")
    for i, n in enumerate((4, 8)):
        write_job(root / str(i), solver="voxel" if i == 0 else "minnorm", n_dips=n, snr_db=None, seed=0, ndim=3,
                  resolution=20, metrics={"iou": 1 - 1 / n, "chamfer": 0.1 / n},
                  history={"data": [1.0, 0.5, 0.2], "tv": [0.1, 0.1, 0.05]} if i == 0 else None)
    write_job(root / "2", solver="minnorm", n_dips=16, snr_db=None, seed=0, metrics=None, error="ValueError: boom")
    return root


def test_run_page_holds_meshes_sinogram_loss_and_metrics(sweep):
    path = report.write_run_report(sweep / "0")
    assert path == sweep / "0" / "report.html"
    text = path.read_text()
    assert text.startswith("<!DOCTYPE html>") and "<script src='../plotly.min.js'>" in text  # shared plotly.js
    for div in ("meshes", "sinogram", "loss"):
        assert f'id="{div}"' in text, div
    assert '"type":"mesh3d"' in text.replace(" ", "") and text.count('"name":"truth"') == 2   # cut open and whole
    assert "<th class=l>intersection over union (1 = identical)</th><td class=l>0.75</td>" in text
    assert "solver=voxel" in text
    # without history.json and without loss.png the page says why there is no curve
    assert "no loss history" in report.write_run_report(sweep / "1").read_text()


def test_a_direct_solver_run_does_not_show_an_earlier_runs_loss(tmp_path):
    """A minnorm run into the folder of an optimiser's run: its reconstruction records no iterations, so the
    history.json and loss.png left there are named as the earlier run's, not drawn as this run's curves."""
    job = write_job(tmp_path / "job", solver="minnorm", n_dips=8, snr_db=None, seed=0, metrics={"iou": 0.7})
    (job / "history.json").write_text(json.dumps({"data": [1.0, 0.5]}))
    (job / "loss.png").write_bytes(b"\x89PNG")
    text = report.write_run_report(job).read_text()
    assert 'id="loss"' not in text
    assert "no loss history (direct solver); history.json and loss.png in this folder are an earlier run's" in text


def test_a_failed_runs_page_says_it_failed_not_empty_or_direct(tmp_path):
    """``python -m dipnet.report`` on a failed sweep job (``solver=voxel_learned resolution=16``: no
    reconstruction.npz): before, its page said "no mesh in this run (empty reconstruction)" and "no loss history
    (direct solver)", neither of which the run was."""
    job = write_job(tmp_path / "job", solver="voxel_learned", n_dips=8, snr_db=None, seed=0, ndim=3, metrics=None,
                    error="PriorMismatchError: the learned prior's weights were trained for a 64^3 grid")
    text = report.write_run_report(job).read_text()
    assert "empty reconstruction" not in text and "direct solver" not in text
    assert text.count("the run wrote no reconstruction.npz: it failed or did not finish") == 2


def test_2d_run_page_shows_images(tmp_path):
    job = write_job(tmp_path / "job", solver="lsmr", n_dips=6, snr_db=20.0, seed=1, ndim=2, resolution=16,
                    metrics={"iou": 0.7})
    text = report.write_run_report(job, tmp_path / "page.html").read_text()
    assert 'id="recon"' in text and 'id="meshes"' not in text and '"type":"heatmap"' in text.replace(" ", "")


def test_sweep_page_links_the_runs_and_lists_failures(sweep, tmp_path):
    runs = collect.collect_runs(sweep)
    report.write_run_report(sweep / "0")
    path = report.write_sweep_report(runs, tmp_path / "cmp" / "report.html", root=sweep)
    text = path.read_text()
    link = re.search(r"<a href='([^']+)'>report</a>", text).group(1)
    assert (path.parent / link).resolve() == (sweep / "0" / "report.html").resolve()
    assert "2 of 3 jobs finished" in text and "ValueError: boom" in text and 'id="vs-dips"' in text


def test_sweep_page_of_recordings_shows_what_they_record(tmp_path):
    for i, solver in enumerate(("minnorm", "lsqr")):
        write_job(tmp_path / "sw" / str(i), solver=solver, n_dips=8, snr_db=None, seed=0, recording="/data/torus.npz",
                  metrics={"profile_residual": 0.1, "volume_ratio": 1.1})
    text = report.write_sweep_report(collect.collect_runs(tmp_path / "sw"), tmp_path / "report.html").read_text()
    assert "these runs have no ground truth (recorded sources)" in text
    assert "<th>profile residual</th><th>volume ratio</th><th>seconds</th>" in text and 'id="vs-dips"' in text


def test_sweep_page_counts_the_empty_runs_and_keeps_their_stand_in_out_of_the_means(tmp_path):
    """Before: the summary's Chamfer 0.505 ± 0.700 held an empty run's 1.0 (a stand-in, one truth diagonal)."""
    for i, (chamfer, empty) in enumerate(((0.01, False), (1.0, True))):
        write_job(tmp_path / "sw" / str(i), solver="minnorm", n_dips=8, snr_db=None, seed=i,
                  metrics={"iou": 0.0 if empty else 0.9, "chamfer": chamfer, "empty": empty})
    text = report.write_sweep_report(collect.collect_runs(tmp_path / "sw"), tmp_path / "report.html").read_text()
    assert "1 of 2 finished runs reconstructed nothing (the empty column)" in text
    assert "<th>runs</th><th>empty</th>" in text and "<td>2</td><td>1 of 2</td>" in text
    assert "<td>0.01 ± 0</td>" in text


def _render(page: Path, tmp_path: Path) -> dict:
    """Load a probed copy of ``page`` in headless Chromium; the probe's JSON."""
    probed = page.parent / f"probed_{page.name}"                      # beside the page: its plotly.min.js loads
    probed.write_text(page.read_text().replace("<head>", "<head>" + PROBE, 1))
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                           "--disable-background-networking", "--virtual-time-budget=10000", "--window-size=1280,2000",
                           "--dump-dom", probed.as_uri()], capture_output=True, text=True, timeout=120)
    found = re.search(r'<pre id="probe">(.*?)</pre>', proc.stdout, re.S)
    assert found, f"no probe output; chromium exit {proc.returncode}: {proc.stderr[-2000:]}"
    return json.loads(html.unescape(found.group(1)))


@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install chromium)")
@pytest.mark.slow
@pytest.mark.seen_first
def test_chromium_shows_the_meshes_without_console_errors(sweep, tmp_path):
    probe = _render(report.write_run_report(sweep / "0"), tmp_path)
    assert probe["errors"] == []
    plots = {p["id"]: p for p in probe["plots"]}
    assert {"meshes", "sinogram", "loss"} <= set(plots)
    meshes = plots["meshes"]
    assert [(t["type"], t["name"]) for t in meshes["traces"]] == \
        [("mesh3d", "truth")] * 2 + [("mesh3d", "reconstruction")] * 2
    assert all(t["faces"] > 100 for t in meshes["traces"][::2])     # the visible, cut-open ones
    assert meshes["canvases"] >= 2                                   # WebGL scenes were created

    runs = collect.collect_runs(sweep)
    sweep_probe = _render(report.write_sweep_report(runs, tmp_path / "sweep.html", root=sweep), tmp_path)
    assert sweep_probe["errors"] == [] and any(p["id"] == "vs-dips" for p in sweep_probe["plots"])


@pytest.fixture()
def answered_sweep(tmp_path):
    """Two 3D jobs whose metrics hold every group (METRICS), with their figures."""
    (tmp_path / "multirun.yaml").write_text("hydra: {}\n")
    for i, n in enumerate((10, 40)):
        job = write_job(tmp_path / str(i), solver="minnorm", n_dips=n, snr_db=None, seed=0, ndim=3, resolution=40,
                        metrics=METRICS)
        for name in ("slices.png", "uncertainty.png", "resolvability.png"):
            (job / name).write_bytes(b"\x89PNG fake")
    return tmp_path


def test_run_pages_share_one_plotly_file_and_stay_under_a_megabyte(answered_sweep):
    from dipnet.experiments import report

    pages = [report.write_run_report(answered_sweep / str(i)) for i in (0, 1)]
    assert sorted(p.name for p in answered_sweep.rglob("plotly.min.js")) == ["plotly.min.js"]  # one, in the sweep dir
    assert (answered_sweep / "plotly.min.js").stat().st_size > 1_000_000
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


def test_the_3d_view_is_cut_open_with_a_button_for_the_whole(answered_sweep):
    from dipnet.experiments import report

    text = report.write_run_report(answered_sweep / "0").read_text()
    spec = json.loads(re.search(r'Plotly.newPlot\(\s*"meshes",\s*(\[.*?\]),\s*(\{.*?\})\s*,\s*\{"responsive"',
                                text, re.S).group(1))
    assert [(t["name"], t.get("visible", True)) for t in spec] == [
        ("truth", True), ("truth", False), ("reconstruction", True), ("reconstruction", False)]
    assert "cut open at y = 0 mm" in text and ">whole<" not in text and '"label":"whole"' in text.replace(" ", "")


def _mesh_traces(text: str) -> list[tuple[str, bool, int]]:
    """``(name, visible, faces)`` of each trace of a run page's 3D view (plotly may encode arrays as base64)."""
    import base64

    import numpy as np

    spec = json.loads(re.search(r'Plotly.newPlot\(\s*"meshes",\s*(\[.*?\]),\s*(\{.*?\})\s*,\s*\{"responsive"',
                                text, re.S).group(1))
    faces = [np.frombuffer(base64.b64decode(t["i"]["bdata"]), t["i"]["dtype"]).size if isinstance(t["i"], dict)
             else len(t["i"]) for t in spec]
    return [(t["name"], t.get("visible", True), n) for t, n in zip(spec, faces)]


def test_the_3d_view_shows_only_the_meshes_the_run_wrote(tmp_path):
    """Before: a run into the folder of an earlier one, with ``output.mesh_formats=[stl]`` or from a recording (no
    truth), showed the earlier run's ``truth.ply`` and ``reconstruction.ply`` as its own (the chamber box on a
    torus run's page, exit 0); with ``[stl]`` alone and no earlier run, no truth at all."""
    import trimesh
    from omegaconf import OmegaConf

    job = write_job(tmp_path / "job", solver="minnorm", n_dips=8, snr_db=None, seed=0, ndim=3, resolution=20,
                    metrics={"iou": 0.9})
    assert [(name, faces > 100) for name, _, faces in _mesh_traces(report.write_run_report(job).read_text())] == [
        ("truth", True), ("truth", True), ("reconstruction", True), ("reconstruction", True)]
    config = OmegaConf.load(job / ".hydra" / "config.yaml")
    config.output = {"mesh_formats": ["stl"]}  # this run: STL files, from a recording (no truth, no shape)
    OmegaConf.save(config, job / ".hydra" / "config.yaml")
    metrics = json.loads((job / "metrics.json").read_text())
    del metrics["shape"], metrics["iou"]
    (job / "metrics.json").write_text(json.dumps(metrics))
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    box.export(job / "reconstruction.stl")
    traces = _mesh_traces(report.write_run_report(job).read_text())
    assert [(name, visible) for name, visible, _ in traces] == [("reconstruction", True), ("reconstruction", False)]
    assert traces[1][2] == len(box.faces)  # the whole box (the first trace is cut open)


def test_the_page_shows_only_the_figures_the_run_drew(tmp_path):
    """Before: the page showed every PNG of the folder: after a run with figures into it, a run with
    ``output.figures=false`` (or without uncertainty, or from a recording: no slices) had the earlier run's
    slices, uncertainty and loss figures on its page, as its own."""
    from omegaconf import OmegaConf

    job = write_job(tmp_path / "job", solver="voxel", n_dips=8, snr_db=None, seed=0, ndim=3, resolution=20,
                    metrics={"iou": 0.9}, history={"data": [1.0, 0.5]})
    (job / "history.json").unlink()  # the loss curves as a PNG only
    names = [name for name, _ in report.RUN_FIGURES] + ["loss.png"]
    for name in names:  # an earlier run's figures
        (job / name).write_bytes(b"\x89PNG\r\n\x1a\n")
    shown = [name for name in names if f'src="{name}"' in report.write_run_report(job).read_text()]
    assert shown == names  # no output options recorded: every figure is taken as the run's
    config = OmegaConf.load(job / ".hydra" / "config.yaml")
    config.output = {"figures": True, "uncertainty": False, "resolvability": True}
    OmegaConf.save(config, job / ".hydra" / "config.yaml")
    metrics = json.loads((job / "metrics.json").read_text())
    del metrics["shape"], metrics["iou"]  # a recording: no truth, no slices
    (job / "metrics.json").write_text(json.dumps(metrics))
    text = report.write_run_report(job).read_text()
    assert [name for name in names if f'src="{name}"' in text] == ["resolvability.png", "profiles.png", "mesh.png",
                                                                   "loss.png"]
    config.output.figures = False
    OmegaConf.save(config, job / ".hydra" / "config.yaml")
    text = report.write_run_report(job).read_text()
    assert not [name for name in names if f'src="{name}"' in text]
