"""HTML reports of one run and of a sweep (needs the optional extra ``report``).

``write_run_report(job_dir)`` writes ``job_dir/report.html``. It opens with the answer: the
truth and the reconstruction in linked interactive 3D views, cut open at the grid's ``y = 0``
plane so inner cavities show (a button shows them whole; 2D runs: the images), beside the three
numbers a person asks first (:func:`dipnet.outputs.summary.answers`: how close, how consistent
with its data, how sure). Then the run's figures (slices, uncertainty, resolvability,
profiles; linked PNG files of the run, not copies), the sinogram, the loss curves, and every
metric of ``metrics.json`` grouped and labelled in words. ``write_sweep_report`` writes one page
for a whole comparison: the summary table, interactive error curves and links to the runs'
own pages.

plotly's JavaScript is loaded from one shared ``plotly.min.js`` file (:data:`PLOTLY_JS`): the
sweep directory holds one for all its jobs' pages and its comparison page (when that is inside
it), a single run directory its own. A run page is then a few hundred kB (meshes decimated to :data:`MAX_FACES`) and
opens offline from its folder.

Install the extra with ``pip install -e ".[report]"`` (plotly).
"""

from __future__ import annotations

import html
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import trimesh

from dipnet.experiments import collect, figures, tables
from dipnet.experiments.collect import GROUP_BY, METRICS, Run
from dipnet.outputs import plots, summary
from dipnet.outputs.progress import planned_stages

REPORT_FILE = "report.html"
#: plotly's JavaScript, written once per folder of reports (see :func:`plotly_js`).
PLOTLY_JS = "plotly.min.js"
#: Faces per mesh in the interactive views (decimated beyond: the page stays small).
MAX_FACES = 6000
#: The run's PNG figures the page shows (those present), with a caption.
RUN_FIGURES = (("slices.png", "mid-plane cuts: truth, reconstruction, missed and extra voxels"),
               ("uncertainty.png", "how sure: posterior std and the probability that each voxel's call is wrong"),
               ("resolvability.png", "what the plan of dips can resolve"),
               ("profiles.png", "measured and predicted dip profiles"),
               ("mesh.png", "rendered meshes, whole and cut open"))
_TRUTH_COLOR, _RECON_COLOR = "#9aa5b1", "#3b7dd8"
_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1200px;color:#222}
h1{font-size:1.5em} h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.9em} \
td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right;white-space:nowrap}
th{background:#f3f3f3} td.l,th.l{text-align:left} .ok{color:#1a7f37} .failed{color:#b42318} .unfinished{color:#b54708}
img{max-width:100%;border:1px solid #eee} .note{color:#666;font-style:italic}
.top{display:grid;grid-template-columns:minmax(0,1fr) 290px;gap:1em;align-items:start}
.answer{border:1px solid #ddd;border-radius:6px;padding:.6em .8em;margin-bottom:.7em;background:#fafafa}
.answer .q{color:#555;font-size:.9em} .answer .h{font-size:1.5em;font-weight:600;margin:.15em 0}
.answer .d{color:#444;font-size:.85em} figure{margin:1em 0} figcaption{color:#555;font-size:.9em}
h3{font-size:1em;margin:1.2em 0 .3em} table.wrap td{white-space:normal;max-width:40em} pre{white-space:pre-wrap}
"""


def require_plotly() -> ModuleType:
    """``plotly.graph_objects``, or an ImportError that says how to install it."""
    try:
        import plotly.graph_objects as go
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError('HTML reports need plotly: pip install -e ".[report]"  (or: pip install plotly)') from exc
    return go


# --------------------------------------------------------------------------- pieces

def mesh_trace(mesh: trimesh.Trimesh, name: str, color: str, scene: str = "scene", visible: bool = True) -> Any:
    """A plotly ``Mesh3d`` of a triangle mesh (vertices in mm), lit, in the given scene."""
    go = require_plotly()
    v, f = np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32)
    return go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], name=name,
                     color=color, flatshading=False, showlegend=True, scene=scene, visible=visible,
                     lighting={"ambient": 0.45, "diffuse": 0.8, "specular": 0.15, "roughness": 0.6,
                               "facenormalsepsilon": 0},
                     lightposition={"x": 200, "y": -300, "z": 500})


def _load_mesh(path: Path) -> trimesh.Trimesh | None:
    if not path.is_file():
        return None
    mesh = trimesh.load(path, force="mesh", process=False)
    return mesh if len(mesh.faces) else None


def _volume_from_npz(job_dir: Path) -> dict[str, np.ndarray] | None:
    path = job_dir / "reconstruction.npz"
    if not path.is_file():
        return None
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def mesh_figure(truth: trimesh.Trimesh | None, recon: trimesh.Trimesh | None,
                origin: Sequence[float] = (0.0, 0.0, 0.0), max_faces: int = MAX_FACES) -> Any:
    """Truth and reconstruction side by side in two 3D scenes with the same axis ranges (the
    meshes' joint bounding box, mm).

    Each mesh (decimated to ``max_faces``) is shown cut open by the plane ``y = origin[1]`` (mm;
    ``origin``: the grid centre in the meshes' frame; the half nearer the camera removed,
    :func:`~dipnet.outputs.plots.cut_away`), so inner cavities show; a button shows the whole meshes.
    """
    require_plotly()
    from plotly.subplots import make_subplots

    panels = [(plots.decimated(m, max_faces), t, c)
              for m, t, c in ((truth, "truth", _TRUTH_COLOR), (recon, "reconstruction", _RECON_COLOR))
              if m is not None]
    fig = make_subplots(rows=1, cols=len(panels), specs=[[{"type": "scene"}] * len(panels)],
                        subplot_titles=[t for _, t, _ in panels], horizontal_spacing=0.02)
    centre = np.asarray(origin, dtype=np.float64)
    bounds = np.concatenate([m.bounds for m, _, _ in panels])
    half = 0.55 * float((bounds.max(axis=0) - bounds.min(axis=0)).max())
    mid = (bounds.max(axis=0) + bounds.min(axis=0)) / 2
    ranges = [[c - half, c + half] for c in mid]
    for i, (mesh, title, color) in enumerate(panels):
        scene = "scene" if i == 0 else f"scene{i + 1}"
        fig.add_trace(mesh_trace(plots.cut_away(mesh, centre[1]), title, color, scene), row=1, col=i + 1)
        fig.add_trace(mesh_trace(mesh, title, color, scene, visible=False), row=1, col=i + 1)
        fig.update_layout({scene: {"xaxis": {"range": ranges[0], "title": "x (mm)"},
                                   "yaxis": {"range": ranges[1], "title": "y (mm)"},
                                   "zaxis": {"range": ranges[2], "title": "z (mm)"}, "aspectmode": "cube",
                                   "camera": {"eye": {"x": 0.9, "y": -1.9, "z": 0.9}}}})
    cut, whole = [True, False] * len(panels), [False, True] * len(panels)
    fig.update_layout(height=520, margin={"l": 0, "r": 0, "t": 60, "b": 0}, showlegend=False,
                      updatemenus=[{"type": "buttons", "direction": "right", "x": 0.5, "y": 1.1, "xanchor": "center",
                                    "buttons": [{"label": f"cut open at y = {centre[1]:.3g} mm", "method": "restyle",
                                                 "args": [{"visible": cut}]},
                                                {"label": "whole", "method": "restyle",
                                                 "args": [{"visible": whole}]}]}])
    return fig


def image_figure(images: Sequence[tuple[str, np.ndarray]], extent_mm: float | None = None) -> Any:
    """2D volumes (``[y, x]``) as heatmaps side by side, y up, in mm when ``extent_mm`` is given."""
    go = require_plotly()
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=1, cols=len(images), subplot_titles=[t for t, _ in images])
    for i, (_, img) in enumerate(images):
        n = img.shape[0]
        axis = (np.arange(n) + 0.5) * extent_mm / n - extent_mm / 2 if extent_mm else np.arange(n)
        fig.add_trace(go.Heatmap(z=np.asarray(img, dtype=np.float32), x=axis, y=axis, colorscale="Greys",
                                 reversescale=True, showscale=False), row=1, col=i + 1)
        fig.update_yaxes(scaleanchor=f"x{i + 1 if i else ''}", row=1, col=i + 1)
    fig.update_layout(height=420, margin={"l": 30, "r": 10, "t": 40, "b": 30})
    return fig


def sinogram_figure(profiles: np.ndarray) -> Any:
    """Slab volumes ``(K, M)`` as a heatmap: orientation index vs slab index."""
    go = require_plotly()
    fig = go.Figure(go.Heatmap(z=np.asarray(profiles, dtype=np.float32), colorscale="Viridis",
                               colorbar={"title": "slab volume"}))
    fig.update_layout(xaxis_title="slab (bottom to top)", yaxis_title="orientation", height=420,
                      margin={"l": 50, "r": 10, "t": 20, "b": 40})
    return fig


def history_figure(history: dict[str, Sequence[float]]) -> Any:
    """Loss terms per iteration (log scale when all positive)."""
    go = require_plotly()
    fig = go.Figure()
    values = []
    for name, series in history.items():
        fig.add_trace(go.Scatter(y=np.asarray(series, dtype=np.float64), mode="lines", name=name))
        values.extend(series)
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    fig.update_layout(xaxis_title="iteration", yaxis_title="value", height=380,
                      yaxis_type="log" if finite.size and (finite > 0).all() else "linear",
                      margin={"l": 50, "r": 10, "t": 20, "b": 40})
    return fig


def metrics_table(items: dict[str, Any]) -> str:
    """A two-column HTML table of scalar values (floats with 4 significant digits)."""
    rows = "".join(f"<tr><th class=l>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>"
                   for k, v in items.items() if not isinstance(v, (dict, list)))
    return f"<table>{rows}</table>"


def grouped_metrics(metrics: dict[str, Any]) -> str:
    """Every entry of ``metrics.json`` under its group (:func:`dipnet.outputs.summary.grouped`):
    a label in words, the value and the key it has in the file."""
    parts = []
    for group, rows in summary.grouped(metrics).items():
        body = "".join(f"<tr><th class=l>{html.escape(label)}</th><td class=l>{html.escape(_fmt(value))}</td>"
                       f"<td class='l note'>{html.escape(key)}</td></tr>" for label, key, value in rows)
        parts.append(f"<h3>{html.escape(group)}</h3><table class=wrap>{body}</table>")
    return "\n".join(parts)


def answers_html(metrics: dict[str, Any]) -> str:
    """The three first answers (:func:`dipnet.outputs.summary.answers`) as cards."""
    cards = [f"<div class=answer><div class=q>{html.escape(a.question)}</div><div class=h>{html.escape(a.headline)}"
             f"</div><div class=d>{html.escape(a.detail)}</div></div>" for a in summary.answers(metrics)]
    return ("<div class=answers>" + ("".join(cards) or "<p class=note>no metrics (the run did not finish)</p>")
            + "</div>")


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return ", ".join(_fmt(x) for x in v)
    if isinstance(v, dict):
        return "; ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    return "none" if v is None else str(v)


def _png(path: Path, alt: str, page_dir: Path) -> str:
    """An ``<img>`` linking a PNG by its path relative to ``page_dir`` (the page's folder)."""
    return f'<img alt="{html.escape(alt)}" src="{html.escape(_relative(path, page_dir))}">'


def _figure_html(fig: Any, div_id: str) -> str:
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id,
                       config={"responsive": True, "displaylogo": False})


def plotly_js(folder: str | Path) -> Path:
    """``folder/plotly.min.js`` (:data:`PLOTLY_JS`), written from the installed plotly unless it
    is already there with the same content; the pages in and below ``folder`` load it."""
    require_plotly()
    from plotly.offline import get_plotlyjs

    path = Path(folder) / PLOTLY_JS
    code = get_plotlyjs()
    if not path.is_file() or path.stat().st_size != len(code.encode("utf-8")):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(code, encoding="utf-8")
    return path


def page(title: str, sections: Sequence[tuple[str, str]], script: str | Path) -> str:
    """A complete HTML page loading plotly from ``script`` (a path relative to the page, e.g.
    from :func:`plotly_js`) with the given ``(heading, html)`` sections (an empty heading: none)."""
    body = "".join((f"<h2>{html.escape(h)}</h2>\n" if h else "") + f"{content}\n" for h, content in sections)
    return (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style><script src='{html.escape(Path(script).as_posix())}'></script></head>"
            f"<body><h1>{html.escape(title)}</h1>\n{body}</body></html>\n")


def report_root(job_dir: Path) -> Path:
    """Where a run page's shared ``plotly.min.js`` goes: the sweep directory of a Hydra sweep job
    (its parent holds ``multirun.yaml``), else the run directory itself."""
    return job_dir.parent if (job_dir.parent / "multirun.yaml").is_file() else job_dir


# --------------------------------------------------------------------------- run page

def run_mesh(job_dir: Path, name: str, formats: Sequence[str]) -> trimesh.Trimesh | None:
    """The mesh ``name`` (``truth`` or ``reconstruction``) a run wrote, in the first of its ``formats``
    (``output.mesh_formats``, e.g. ``["stl"]``) found in ``job_dir``; ``None`` when there is none or it is empty."""
    for fmt in formats:
        mesh = _load_mesh(job_dir / f"{name}.{str(fmt).lower()}")
        if mesh is not None:
            return mesh
    return None


#: Why a run's page has no result to show when its folder holds no ``reconstruction.npz``.
NO_RESULT = "the run wrote no reconstruction.npz: it failed or did not finish"


def _shape_view(job_dir: Path, volume: dict[str, np.ndarray] | None, ndim: Any, metrics: dict[str, Any],
                formats: Sequence[str] = ("ply",)) -> str:
    """The interactive view of the result: images (2D) or meshes cut open (3D), read in the run's mesh
    ``formats``. A mesh file the run did not write is not shown: a truth only when the run has one (its
    metrics name the ``shape``: a recording has none), a reconstruction only when its volume is not empty
    (an earlier run into the folder may have left either)."""
    extent = float(volume["grid_extent"]) if volume is not None and "grid_extent" in volume else None
    if ndim == 2 and volume is not None:
        images = [("reconstruction (binary)", volume["binary"]), ("occupancy", volume["occupancy"])]
        return _figure_html(image_figure(images, extent), "recon")
    truth = run_mesh(job_dir, "truth", formats) if metrics.get("shape") is not None else None
    empty = volume is not None and not volume["binary"].any()
    recon = None if empty else run_mesh(job_dir, "reconstruction", formats)
    origin = np.asarray(metrics.get("frame_offset_mm") or (0.0, 0.0, 0.0), dtype=np.float64)
    if recon is None and volume is not None and volume["binary"].any():
        from dipnet.shapes.isosurface import volume_to_mesh
        from dipnet.core.grid import Grid

        grid = Grid(int(volume["grid_n"]), 3, float(volume["grid_extent"]))
        recon = volume_to_mesh(volume["occupancy"], grid, float(volume["threshold"])).apply_translation(origin)
    if truth is None and recon is None:
        return f"<p class=note>no mesh in this run ({'empty reconstruction' if volume is not None else NO_RESULT})</p>"
    return _figure_html(mesh_figure(truth, recon, origin), "meshes")


def drawn_figures(output: dict[str, Any], truth: bool, ndim: Any) -> set[str]:
    """The PNG figures a run with these ``output`` options draws (``truth``: its shape is known; ``ndim``: 2 or 3):
    none with ``figures: false``; the slices with a truth, the uncertainty and resolvability figures when their
    stages run (:func:`~dipnet.outputs.progress.planned_stages`), the rendered meshes in 3D. A figure of another
    name in the run folder is an earlier run's (the same ``hydra.run.dir``), not this run's. Without ``output``
    options (a run folder without its ``.hydra/config.yaml``) every figure there is taken as the run's."""
    if not output:
        return {name for name, _ in RUN_FIGURES} | {"loss.png"}
    if output.get("figures", True) is False:
        return set()
    stages = planned_stages(output, truth)
    return {"profiles.png", "loss.png"} | {name for name, drawn in (
        ("slices.png", truth), ("uncertainty.png", "uncertainty" in stages),
        ("resolvability.png", "resolvability" in stages), ("mesh.png", ndim == 3)) if drawn}


def run_sections(job_dir: str | Path, page_dir: str | Path | None = None) -> list[tuple[str, str]]:
    """The sections of one run's page (see the module docstring), from the files in ``job_dir``;
    its PNG figures are linked relative to ``page_dir`` (default ``job_dir``)."""
    job_dir = Path(job_dir)
    page_dir = Path(page_dir) if page_dir is not None else job_dir
    run = collect.load_run(job_dir)
    row = collect.run_row(run)
    volume = _volume_from_npz(job_dir)
    ndim = int(volume["grid_ndim"]) if volume is not None else row.get("ndim")
    status = "" if run.status == "ok" else f"<p class={run.status}>{html.escape(run.status)}: " \
        f"{html.escape(run.error or 'no metrics.json')}</p>"
    formats = (run.config.get("output") or {}).get("mesh_formats") or ["ply"]
    view = _shape_view(job_dir, volume, ndim, run.metrics, formats)
    sections: list[tuple[str, str]] = [
        ("", f"{status}<div class=top><div class=view>{view}</div>{answers_html(run.metrics)}</div>")]

    drawn = drawn_figures(run.config.get("output") or {}, run.metrics.get("shape") is not None, ndim)
    figures_html = [f"<figure>{_png(job_dir / name, name, page_dir)}<figcaption>{html.escape(caption)}"
                    f"</figcaption></figure>" for name, caption in RUN_FIGURES
                    if name in drawn and (job_dir / name).is_file()]
    if figures_html:
        sections.append(("figures", "\n".join(figures_html)))

    if (job_dir / "measurement.npz").is_file():
        from dipnet.core.measurement import DipMeasurement

        profiles = DipMeasurement.load(job_dir / "measurement.npz").profiles.numpy()
        sections.append(("sinogram (measured slab volumes)", _figure_html(sinogram_figure(profiles), "sinogram")))

    sections.append(("loss", _loss_html(job_dir, page_dir, volume, "loss.png" in drawn)))

    settings = {k: row.get(k) for k in ("status", "solver", "shape", "ndim", "resolution", "n_dips",
                                        "dips_percent", "snr_db", "seed") if row.get(k) is not None or k == "snr_db"}
    sections.append(("every metric (metrics.json)",
                     grouped_metrics({**settings, **run.metrics}) if run.metrics else metrics_table(settings)))
    if run.overrides:
        sections.append(("overrides", f"<pre>{html.escape(' '.join(run.overrides))}</pre>"))
    return sections


def _loss_html(job_dir: Path, page_dir: Path, volume: dict[str, np.ndarray] | None, drawn: bool) -> str:
    """The loss curves from ``history.json`` (else ``loss.png`` when the run draws it), or why there are none.
    A run whose ``reconstruction.npz`` records no iterations (``history_steps`` 0: a direct solver) shows none,
    whatever an earlier run into the folder left there."""
    direct = volume is not None and "history_steps" in volume and int(volume["history_steps"]) == 0
    if direct:
        left = [name for name in ("history.json", "loss.png") if (job_dir / name).is_file()]
        return ("<p class=note>no loss history (direct solver)" +
                (f"; {html.escape(' and '.join(left))} in this folder are an earlier run's" if left else "") + "</p>")
    if (job_dir / "history.json").is_file():
        history = json.loads((job_dir / "history.json").read_text())
        return _figure_html(history_figure(history), "loss")
    if drawn and (job_dir / "loss.png").is_file():
        return _png(job_dir / "loss.png", "loss curves", page_dir)
    return f"<p class=note>no loss history ({'direct solver' if volume is not None else NO_RESULT})</p>"


def write_run_report(job_dir: str | Path, path: str | Path | None = None) -> Path:
    """Write one run's page (default ``job_dir/report.html``) and return its path; plotly's
    JavaScript goes to :func:`report_root` (or beside a page written elsewhere)."""
    job_dir = Path(job_dir)
    if not job_dir.is_dir():
        raise FileNotFoundError(f"{job_dir}: not a run directory")
    path = Path(path) if path is not None else job_dir / REPORT_FILE
    row = collect.run_row(collect.load_run(job_dir))
    title = f"dipnet run {job_dir.name}: {row.get('solver')}, {row.get('shape')}, {row.get('n_dips')} dips"
    script = plotly_js(report_root(job_dir) if path.parent.resolve() == job_dir.resolve() else path.parent)
    path.write_text(page(title, run_sections(job_dir, path.parent), _relative(script, path.parent)), encoding="utf-8")
    return path


# --------------------------------------------------------------------------- sweep page

def curves_figure(groups: Sequence[dict], x: str, metrics: Sequence[str], line: str = "solver",
                  log_x: bool = True) -> Any:
    """Mean ± std of ``metrics`` vs ``x`` (one line per ``line`` value), one panel per metric."""
    go = require_plotly()
    from plotly.subplots import make_subplots

    panels = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    fig = make_subplots(rows=1, cols=max(len(panels), 1), subplot_titles=[collect.LABELS.get(m, m) for m in panels])
    palette = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f"]
    for col, metric in enumerate(panels, start=1):
        for i, (key, (xs, mean, std)) in enumerate(figures.mean_series(groups, line, x, metric).items()):
            fig.add_trace(go.Scatter(x=xs, y=mean, error_y={"type": "data", "array": std}, mode="lines+markers",
                                     name=tables.format_cell(key), legendgroup=str(key), showlegend=col == 1,
                                     line={"color": palette[i % len(palette)]}), row=1, col=col)
        fig.update_xaxes(title_text=collect.LABELS.get(x, x), type="log" if log_x else "linear", row=1, col=col)
    fig.update_layout(height=400, margin={"l": 50, "r": 10, "t": 40, "b": 40},
                      legend_title_text=collect.LABELS.get(line, line))
    return fig


def _runs_table(runs: Sequence[Run], root: Path, out_dir: Path) -> str:
    cols = ("job", "status", "solver", "shape", "n_dips", "snr_db", "seed", "iou", "chamfer", "seconds")
    head = "".join(f"<th class=l>{c}</th>" for c in cols) + "<th class=l>page / error</th>"
    body = []
    for run, row in zip(runs, collect.run_rows(runs, root)):
        cells = "".join(f"<td class='l {row['status'] if c == 'status' else ''}'>{html.escape(_fmt(row.get(c)))}</td>"
                        for c in cols)
        page_path = run.path / REPORT_FILE
        if page_path.is_file():
            extra = f"<a href='{html.escape(_relative(page_path, out_dir))}'>report</a>"
        else:
            extra = html.escape(run.error or "")
        body.append(f"<tr>{cells}<td class=l>{extra}</td></tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _relative(target: Path, start: Path) -> str:
    return Path(os.path.relpath(target.resolve(), start.resolve())).as_posix()


def write_sweep_report(runs: Sequence[Run], path: str | Path, *, root: str | Path | None = None,
                       by: Sequence[str] = GROUP_BY, images: Sequence[str | Path] = ()) -> Path:
    """Write the comparison page of a sweep: summary table (mean ± std per ``by`` group),
    interactive IoU / Chamfer vs dips (runs without a truth: profile residual / volume ratio,
    :func:`~dipnet.experiments.collect.compared_metrics`) and FP / FN vs SNR curves, the given PNG ``images``
    (e.g. the montage), and every job with its status and a link to its own page."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    root = Path(root) if root is not None else path.parent
    rows = collect.run_rows(runs, root)
    metrics = collect.compared_metrics(rows)
    groups = collect.aggregate(rows, by, metrics)
    n_ok = sum(r.status == "ok" for r in runs)
    notes = [line for line in (collect.truth_note(rows), collect.empty_note(rows)) if line]
    sections = [("summary", f"<p>{n_ok} of {len(runs)} jobs finished.</p>"
                 + "".join(f"<p class=note>{html.escape(line)}</p>" for line in notes)
                 + _groups_table(groups, by, metrics))]
    if any("n_dips" in g for g in groups) and "n_dips" in by:
        curves = collect.curve_groups(rows, "n_dips", metrics)
        sections.append(("error vs number of dips", _figure_html(
            curves_figure(curves, "n_dips", collect.curve_metrics(metrics), line="series"), "vs-dips")))
    if "snr_db" in by and any(isinstance(g.get("snr_db"), (int, float)) for g in groups):
        curves = collect.curve_groups(rows, "snr_db", metrics)
        metrics = [m for m in ("false_positive", "false_negative") if any(f"{m}_mean" in g for g in curves)] or ["iou"]
        sections.append(("error vs SNR", _figure_html(curves_figure(curves, "snr_db", metrics, line="series",
                                                                    log_x=False), "vs-snr")))
    for image in images:
        image = Path(image)
        if image.is_file():
            sections.append((image.stem, _png(image, image.stem, path.parent)))
    sections.append(("jobs", _runs_table(runs, root, path.parent)))
    inside = path.parent.resolve().is_relative_to(root.resolve())  # e.g. <sweep>/compare: the jobs' file
    script = _relative(plotly_js(root if inside else path.parent), path.parent)
    path.write_text(page(f"dipnet sweep: {root}", sections, script), encoding="utf-8")
    return path


def _groups_table(groups: Sequence[dict], by: Sequence[str], metrics: Sequence[str] = METRICS) -> str:
    present = [m for m in metrics if any(f"{m}_mean" in g for g in groups)]
    empties = any("empty" in g for g in groups)  # runs that reconstructed nothing: counted, not in the means
    failures = any("failed" in g for g in groups)  # jobs that failed: counted, not in the means
    head = "".join(f"<th class=l>{collect.LABELS.get(k, k)}</th>" for k in by) + "<th>runs</th>" + \
        ("<th>failed</th>" if failures else "") + ("<th>empty</th>" if empties else "") + \
        "".join(f"<th>{collect.LABELS.get(m, m)}</th>" for m in present)
    body = []
    for g in groups:
        cells = "".join(f"<td class=l>{html.escape(tables.format_cell(g.get(k)))}</td>" for k in by)
        cells += f"<td>{g['runs']}</td>" + (f"<td>{g.get('failed', 0)}</td>" if failures else "")
        cells += f"<td>{g.get('empty', 0)} of {g['runs']}</td>" if empties else ""
        cells += "".join(f"<td>{g[f'{m}_mean']:.4g} ± {g[f'{m}_std']:.2g}</td>" if f"{m}_mean" in g else
                         f"<td>{html.escape(tables.metric_cell(g, m))}</td>" for m in present)
        body.append(f"<tr>{cells}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m dipnet.report JOB_DIR [JOB_DIR ...]``: write each run's ``report.html``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m dipnet.report",
                                     description="Write report.html into reconstruction job directories.")
    parser.add_argument("jobs", nargs="+", type=Path, help="job directories (Hydra run or sweep job dirs)")
    args = parser.parse_args(argv)
    for job in args.jobs:  # every one before any page: a missing folder was a traceback, an empty one got a page
        if not collect.is_job_dir(job):
            what = "not a folder" if not job.is_dir() else \
                "holds no run (no .hydra/config.yaml, metrics.json or error.txt)"
            print(f"error: {job}: {what}: give the run directory of a reconstruct.py job (a sweep's jobs: "
                  "scripts/compare.py SWEEP --html)", file=sys.stderr)
            return 2
    for job in args.jobs:
        print(write_run_report(job))
    return 0
