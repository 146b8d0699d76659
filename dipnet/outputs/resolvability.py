"""What the plan resolves, into the run directory: ``resolvability.npz`` and its four-panel figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.evaluation.resolvability import Resolvability, angle_to_plan, resolvability
from dipnet.outputs.plots import plt, save_figure  # matplotlib with the Agg backend


def plot_resolvability(res: Resolvability, path: str | Path, title: str = "what the plan resolves") -> Path:
    """Four panels: the hemisphere of directions coloured by their angle to the plan (the
    missing cone), the covered frequencies in a vertical (k_x, k_z) and in the horizontal
    (k_x, k_y) plane, and the covered share per frequency polar angle. 2D plans: the first,
    second and last panel only."""
    three_d = res.directions.shape[1] == 3
    fig, axes = plt.subplots(1, 4 if three_d else 3, figsize=(18 if three_d else 13, 4.4), layout="constrained")
    ax = axes[0]
    if three_d:  # the hemisphere seen from above: (x, y) = (sin tilt cos azimuth, sin tilt sin azimuth)
        xy = np.linspace(-1, 1, 161)
        x, y = np.meshgrid(xy, xy)
        disk = x**2 + y**2 <= 1
        pts = np.stack([x[disk], y[disk], np.sqrt(np.clip(1 - x[disk] ** 2 - y[disk] ** 2, 0, 1))], axis=1)
        img = np.full(x.shape, np.nan)
        img[disk] = np.degrees(angle_to_plan(pts, res.directions))
        im = ax.imshow(img, origin="lower", extent=(-1, 1, -1, 1), cmap="magma_r", vmin=0, vmax=90)
        d = res.directions * np.where(res.directions[:, 2:] < 0, -1.0, 1.0)
        ax.scatter(d[:, 0], d[:, 1], s=6, c="cyan", edgecolors="k", linewidths=0.3)
        ax.set_xlabel("x = sin(tilt) cos(azimuth)")
        ax.set_ylabel("y = sin(tilt) sin(azimuth)")
        fig.colorbar(im, ax=ax, label="angle to the nearest dip (deg)", shrink=0.8)
    else:
        a = np.degrees(np.arctan2(res.sphere[:, 1], res.sphere[:, 0]))
        ax.plot(a, res.gap_deg)
        for t in np.degrees(np.arctan2(res.directions[:, 1], res.directions[:, 0])) % 180:
            ax.axvline(t, color="c", lw=0.5)
        ax.set_xlabel("direction (deg)")
        ax.set_ylabel("angle to the nearest dip (deg)")
    ax.set_title(f"missing cone {res.missing_cone_deg:.0f} deg")
    cov = np.fft.fftshift(res.coverage)
    n = cov.shape[0]
    extent = (-1, 1, -1, 1)
    slices = [("k_x", "k_z", cov[:, n // 2, :], ""), ("k_x", "k_y", cov[n // 2, :, :], ", k_z = 0")] if three_d \
        else [("k_x", "k_y", cov, "")]
    for ax, (xl, yl, img, note) in zip(axes[1:], slices):
        ax.imshow(img, origin="lower", extent=extent, cmap="Greens", vmin=0, vmax=1.5, interpolation="nearest")
        ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="k", lw=0.5))
        ax.set_xlabel(f"{xl} / Nyquist")
        ax.set_ylabel(f"{yl} / Nyquist")
        ax.set_title(f"covered frequencies ({xl}, {yl}){note}")
    ax = axes[-1]
    ax.plot(res.polar_deg, res.coverage_by_polar, "o-")
    ax.set_xlabel("frequency angle from the vertical axis (deg)")
    ax.set_ylabel("covered share of the frequency ball")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"polar {res.polar_coverage:.2f} / azimuthal {res.azimuthal_coverage:.2f}")
    fig.suptitle(title)
    return save_figure(fig, path)


def write_resolvability(measurement: DipMeasurement, grid: Grid, out: str | Path, figure: bool = True) -> dict:
    """:func:`resolvability` of a measurement's plan on ``grid``: ``resolvability.npz`` (and
    ``resolvability.png`` with ``figure``) in the folder ``out``; returns the summary metrics."""
    out = Path(out)
    res = resolvability(measurement.directions, grid, measurement)
    res.save(out / "resolvability.npz")
    if figure:
        plot_resolvability(res, out / "resolvability.png")
    return res.metrics()
