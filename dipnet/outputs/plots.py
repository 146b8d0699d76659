"""Figures of a run, as PNG files (matplotlib, Agg backend: no display needed).

Every function writes one PNG and returns its path. Volumes follow :mod:`dipnet.core.grid`
(``[z, y, x]`` / ``[y, x]``); slices are drawn with ``x`` to the right and ``y`` (or ``z``) up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

MAX_RENDER_FACES = 4000
_LIGHT = np.array([0.4, -0.5, 0.77]) / np.linalg.norm([0.4, -0.5, 0.77])


def _numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def save_figure(fig: plt.Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (PNG, parents created), close it and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _volume_label(two_d: bool) -> str:
    """Axis label of slab volumes: mm^3, or mm^2 for 2D areas."""
    return "slab area (mm$^2$)" if two_d else "slab volume (mm$^3$)"


def plot_sinogram(profiles: np.ndarray | torch.Tensor, path: str | Path, *,
                  angles_deg: Sequence[float] | None = None,
                  slab_edges: np.ndarray | torch.Tensor | None = None, title: str = "dip profiles",
                  volume_unit_2d: bool = False) -> Path:
    """Slab volumes vs orientation as an image: ``profiles`` ``(K, M)`` (mm^3, mm^2 in 2D).

    ``angles_deg`` (2D, ``(K,)``) labels the orientation axis with angles; otherwise rows are
    orientation indices (3D). ``slab_edges`` ``(M + 1,)`` (mm, e.g. ``operator.slab_edges()``)
    puts the height ``t`` on the slab axis.
    """
    p = _numpy(profiles).astype(np.float64)
    if p.ndim != 2:
        raise ValueError(f"profiles must have shape (K, M), got {p.shape}")
    k, m = p.shape
    if slab_edges is not None:
        e = _numpy(slab_edges).astype(np.float64)
        height = (float(e[0]), float(e[-1]), "height t (mm)")
    else:
        height = (0.0, float(m), "slab")
    if angles_deg is not None:
        a = np.asarray(angles_deg, dtype=np.float64)
        rows = (a.min(), a.max() + (a[1] - a[0] if k > 1 else 1.0), "orientation (deg)")
    else:
        rows = (0.0, float(k), "orientation index")
    fig, ax = plt.subplots(figsize=(6, 4.5))
    im = ax.imshow(p, aspect="auto", origin="lower", cmap="viridis", interpolation="nearest",
                   extent=(height[0], height[1], rows[0], rows[1]))
    ax.set(xlabel=height[2], ylabel=rows[2], title=title)
    fig.colorbar(im, ax=ax, label=_volume_label(volume_unit_2d))
    return save_figure(fig, path)


@dataclass
class Slice:
    """One planar cut of a volume: its title (with the plane's position), the image (rows up)
    and the names of its horizontal and vertical axes."""

    name: str
    image: np.ndarray
    xlabel: str
    ylabel: str


def mid_slices(vol: np.ndarray, extent_mm: float | None = None) -> list[Slice]:
    """The image itself in 2D; in 3D the mid-plane cuts ``z``, ``y``, ``x`` of a ``[z, y, x]``
    volume, titled with their position (mm when the grid side ``extent_mm`` is given, else
    the voxel index)."""
    unit = "mm" if extent_mm else "voxels"
    if vol.ndim == 2:
        return [Slice("image", vol, f"x ({unit})", f"y ({unit})")]
    n = vol.shape[0] // 2
    at = f"{-extent_mm / 2 + (n + 0.5) * extent_mm / vol.shape[0]:.3g} mm" if extent_mm else f"index {n}"
    return [Slice(f"z = {at}", vol[n], f"x ({unit})", f"y ({unit})"),
            Slice(f"y = {at}", vol[:, n, :], f"x ({unit})", f"z ({unit})"),
            Slice(f"x = {at}", vol[:, :, n], f"y ({unit})", f"z ({unit})")]


def show_slice(ax: plt.Axes, cut: Slice, extent_mm: float | None, title: str, **imshow: Any) -> Any:
    """Draw ``cut`` on ``ax`` with mm axes (voxel indices without ``extent_mm``); returns the image."""
    rows, cols = cut.image.shape
    box = (-extent_mm / 2, extent_mm / 2, -extent_mm / 2, extent_mm / 2) if extent_mm else (0, cols, 0, rows)
    im = ax.imshow(cut.image, origin="lower", interpolation="nearest", extent=box, **imshow)
    ax.set_title(f"{title}: {cut.name}", fontsize=9)
    ax.set_xlabel(cut.xlabel, fontsize=8)
    ax.set_ylabel(cut.ylabel, fontsize=8)
    ax.tick_params(labelsize=7)
    return im


def _zoom(occupied: np.ndarray, extent_mm: float | None, margin: int = 2) -> tuple[float, float]:
    """Axis limits (mm, or voxel units without ``extent_mm``) around the occupied voxels of a
    cube ``occupied`` plus ``margin`` voxels, the same on every axis; the whole grid if none is."""
    n = occupied.shape[0]
    idx = np.argwhere(occupied)
    reach = n / 2 if not len(idx) else min(float(np.abs(idx + 0.5 - n / 2).max()) + margin, n / 2)
    scale = extent_mm / n if extent_mm else 1.0
    centre = 0.0 if extent_mm else n / 2
    return centre - reach * scale, centre + reach * scale


#: Colours of the difference panels: agreement (transparent), missed and extra voxels.
MISSED_COLOR, EXTRA_COLOR = "#d62728", "#1f77b4"


def plot_slices(truth: np.ndarray | torch.Tensor, recon: np.ndarray | torch.Tensor, path: str | Path, *,
                titles: tuple[str, str] = ("truth", "reconstruction"), extent_mm: float | None = None,
                truth_level: float = 0.5) -> Path:
    """Truth, reconstruction and where they differ: the image in 2D, mid-plane cuts along the
    three axes in 3D (one row per axis), on mm axes when the grid side ``extent_mm`` is given.

    Volumes ``grid.shape``, occupancy-like values; the truth counts as inside above
    ``truth_level``, the reconstruction above 0.5. The difference panel colours the *missed*
    voxels (in the truth, not reconstructed) and the *extra* ones (reconstructed, not in the
    truth) over the faint truth, with a legend giving their counts in the cut.
    """
    t, r = _numpy(truth).astype(np.float64), _numpy(recon).astype(np.float64)
    if t.shape != r.shape or t.ndim not in (2, 3):
        raise ValueError(f"truth and reconstruction must be 2D or 3D volumes of one shape, got {t.shape}, {r.shape}")
    inside_t, inside_r = t > truth_level, r > 0.5
    code = np.where(inside_t & ~inside_r, 1, np.where(inside_r & ~inside_t, 2, 0)).astype(float)
    rows = list(zip(mid_slices(t, extent_mm), mid_slices(r, extent_mm), mid_slices(code, extent_mm)))
    lo, hi = min(t.min(), r.min()), max(t.max(), r.max())
    cmap = matplotlib.colors.ListedColormap([MISSED_COLOR, EXTRA_COLOR])
    zoom = _zoom(inside_t | inside_r, extent_mm)
    fig, axes = plt.subplots(len(rows), 3, figsize=(11, 3.5 * len(rows) + 0.6), squeeze=False, layout="constrained")
    for row, (ts, rs, cs) in zip(axes, rows):
        show_slice(row[0], ts, extent_mm, titles[0], vmin=lo, vmax=hi, cmap="gray")
        show_slice(row[1], rs, extent_mm, titles[1], vmin=lo, vmax=hi, cmap="gray")
        show_slice(row[2], Slice(cs.name, ts.image, cs.xlabel, cs.ylabel), extent_mm, "difference",
                   vmin=lo, vmax=hi + 3 * (hi - lo), cmap="Greys")  # the truth, faint
        show_slice(row[2], Slice(cs.name, np.ma.masked_equal(cs.image, 0), cs.xlabel, cs.ylabel), extent_mm,
                   "difference", vmin=1, vmax=2, cmap=cmap)
        for ax in row:
            ax.set(xlim=zoom, ylim=zoom)
        missed, extra = int((cs.image == 1).sum()), int((cs.image == 2).sum())
        row[2].legend(handles=[Patch(color=MISSED_COLOR, label=f"missed ({missed})"),
                               Patch(color=EXTRA_COLOR, label=f"extra ({extra})")],
                      fontsize=7, loc="upper right", framealpha=0.8)
    fig.suptitle("missed: in the truth, not reconstructed; extra: reconstructed, not in the truth "
                 "(voxels in each cut)", fontsize=9)
    return save_figure(fig, path)


def decimated(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """At most ``max_faces`` faces (quadric decimation by libigl; the mesh itself if that fails)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    try:
        import igl

        out = igl.decimate(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), max_faces)
        verts, faces = (out[1], out[2]) if isinstance(out[0], (bool, np.bool_)) else (out[0], out[1])
        if len(faces):
            return trimesh.Trimesh(verts, faces, process=False)
    except Exception:  # noqa: BLE001 - decimation is only a speed-up for drawing
        pass
    return mesh


def plot_mesh(meshes: trimesh.Trimesh | Sequence[trimesh.Trimesh], path: str | Path, *,
              titles: Sequence[str] | None = None, max_faces: int = MAX_RENDER_FACES,
              elev: float = 25.0, azim: float = -60.0, cutaway: bool = True) -> Path:
    """Shaded renderings of one or several meshes side by side (Lambert shading, one light),
    all in the same box (mm).

    ``cutaway``: a second row shows each mesh cut open by the plane ``y = 0`` (the half at
    ``y >= 0``, seen from ``-y``), so interior cavities (the chamber box's hidden chamber) show.
    Meshes with more than ``max_faces`` faces are decimated for drawing; empty meshes are
    drawn as an empty panel saying so.
    """
    meshes = [meshes] if isinstance(meshes, trimesh.Trimesh) else list(meshes)
    titles = list(titles) if titles is not None else [""] * len(meshes)
    if len(titles) != len(meshes):
        raise ValueError(f"got {len(titles)} titles for {len(meshes)} meshes")
    drawn = [m for m in meshes if len(m.faces)]
    box = None
    if drawn:  # one box for every panel, so sizes compare
        lo = np.min([m.bounds[0] for m in drawn], axis=0)
        hi = np.max([m.bounds[1] for m in drawn], axis=0)
        box = ((lo + hi) / 2, (hi - lo).max() / 2)
    rows = [(m, t, elev, azim) for m, t in zip(meshes, titles)]
    if cutaway:
        rows += [(cut_away(m), f"{t} (cut at y = 0)".strip(), 10.0, -90.0) for m, t in zip(meshes, titles)]
    n_rows = 2 if cutaway else 1
    fig = plt.figure(figsize=(4.5 * len(meshes), 4.5 * n_rows))
    for i, (mesh, title, el, az) in enumerate(rows):
        ax = fig.add_subplot(n_rows, len(meshes), i + 1, projection="3d")
        _draw_mesh(ax, mesh, title, box, max_faces, el, az)
    return save_figure(fig, path)


def cut_away(mesh: trimesh.Trimesh, y0: float = 0.0) -> trimesh.Trimesh:
    """The faces of ``mesh`` with every vertex at ``y >= y0`` (mm): an open cut, to the nearest
    face, so seen from ``-y`` the inside walls show through."""
    if len(mesh.faces) == 0:
        return mesh
    faces = np.asarray(mesh.faces)
    keep = (np.asarray(mesh.vertices)[faces][:, :, 1] >= y0).all(axis=1)
    cut = trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=faces[keep], process=False)
    cut.remove_unreferenced_vertices()
    return cut


def _draw_mesh(ax, mesh: trimesh.Trimesh, title: str, box, max_faces: int, elev: float, azim: float) -> None:
    ax.set_title(title)
    if len(mesh.faces) == 0 or box is None:
        ax.text2D(0.5, 0.5, "empty mesh", ha="center", transform=ax.transAxes)
        ax.set_axis_off()
        return
    m = decimated(mesh, max_faces)
    tris = np.asarray(m.vertices)[np.asarray(m.faces)]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    shade = 0.25 + 0.75 * np.abs(normals @ _LIGHT)  # both sides lit: a cut shows inner walls
    colors = np.column_stack([0.35 * shade, 0.55 * shade, 0.85 * shade, np.ones_like(shade)])
    ax.add_collection3d(Poly3DCollection(tris, facecolors=colors, edgecolors="none"))
    centre, half = box
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(centre[2] - half, centre[2] + half), xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)")
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)


def plot_history(history: dict[str, Sequence[float]], path: str | Path, *, title: str = "loss") -> Path:
    """Loss curves ``{name: values per iteration}``; log scale when every value is positive."""
    series = {k: np.asarray(v, dtype=np.float64) for k, v in history.items() if len(v)}
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, values in series.items():
        ax.plot(np.arange(len(values)), values, label=name)
    values = np.concatenate(list(series.values())) if series else np.zeros(0)
    finite = values[np.isfinite(values)]
    if finite.size and (finite > 0).all():
        ax.set_yscale("log")
    elif finite.size:
        ax.set_yscale("symlog", linthresh=max(float(np.abs(finite).max()) * 1e-6, 1e-12))
    ax.set(xlabel="iteration", ylabel="value", title=title)
    if series:
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no history", ha="center", transform=ax.transAxes)
    return save_figure(fig, path)


def plot_profiles(measured: np.ndarray | torch.Tensor, predicted: np.ndarray | torch.Tensor | None,
                  path: str | Path, *, k: int | Sequence[int] = 4,
                  slab_edges: np.ndarray | torch.Tensor | None = None,
                  labels: tuple[str, str] = ("measured", "predicted"), volume_unit_2d: bool = False) -> Path:
    """A few profiles overlaid: measured (markers) and predicted (lines), ``(K, M)`` each, in
    mm^3 (``volume_unit_2d``: mm^2).

    ``k``: how many orientations (spread evenly over ``K``), or their indices; ``slab_edges``
    ``(M + 1,)`` (mm) puts the height ``t`` on the horizontal axis.
    """
    meas = _numpy(measured).astype(np.float64)
    pred = None if predicted is None else _numpy(predicted).astype(np.float64)
    if meas.ndim != 2 or (pred is not None and pred.shape != meas.shape):
        raise ValueError(f"profiles must be (K, M) arrays of one shape, got {meas.shape}"
                         + ("" if pred is None else f" and {pred.shape}"))
    idx = (np.unique(np.linspace(0, meas.shape[0] - 1, int(k)).round().astype(int)) if np.isscalar(k)
           else np.asarray(k, dtype=int))
    if slab_edges is not None:
        e = _numpy(slab_edges).astype(np.float64)
        x = (e[:-1] + e[1:]) / 2
    else:
        x = np.arange(meas.shape[1]) + 0.5
    fig, ax = plt.subplots(figsize=(7, 4))
    for i, colour in zip(idx, plt.rcParams["axes.prop_cycle"].by_key()["color"] * (len(idx) // 10 + 1)):
        ax.plot(x, meas[i], ".", color=colour, label=f"{labels[0]} #{i}")
        if pred is not None:
            ax.plot(x, pred[i], "-", color=colour, label=f"{labels[1]} #{i}")
    ax.set(xlabel="height t (mm)" if slab_edges is not None else "slab index", ylabel=_volume_label(volume_unit_2d),
           title="dip profiles")
    ax.legend(fontsize=7, ncol=2)
    return save_figure(fig, path)
