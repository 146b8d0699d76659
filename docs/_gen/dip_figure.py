"""Draw ``docs/dip_profile.png``, the README's picture of what one dip measures (run by hand, not at build).

    python docs/_gen/dip_figure.py

Left: the built-in 2D chamber box (a square with an inner chamber reached through a narrow channel) dipped
along one direction, the water line part-way through, the slabs it is cut into. Right: that dip's profile, the
area of every slab (mm^2; in 3D, volumes in mm^3) from the project's own dip operator, the submerged slabs in
blue: the water's rise times the tank's section after each step. The chamber's slabs hold less: the water
fills it, so the dip sees the cavity.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import dipnet  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "dip_profile.png"
ANGLE_DEG = 70.0       # the dip direction (the object's "up" vector), from the x axis
WATER_T = 8.0          # the water line, as a height t = x . theta (mm)


def main() -> None:
    grid = dipnet.Grid(160, ndim=2, extent=100.0)
    shape = dipnet.builtin_shape("chamber_box", 2, radius=0.9 * grid.radius)
    occupancy = shape.occupancy(grid, supersample=3)                       # (160, 160), [y, x]
    theta = dipnet.directions_2d([ANGLE_DEG])                              # (1, 2)
    op = dipnet.make_operator(grid, theta, n_slabs=32)
    profile = op(occupancy)[0].numpy()                                     # (32,) mm^2 per slab
    edges = op.slab_edges().numpy()
    centres = 0.5 * (edges[1:] + edges[:-1])

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(8.0, 3.4), gridspec_kw={"width_ratios": [1, 1.4]})
    half = grid.extent / 2
    ax.imshow(occupancy.numpy(), origin="lower", extent=(-half, half, -half, half), cmap="Greys", vmin=0, vmax=1.6)
    xs = grid.axis().numpy()
    x, y = np.meshgrid(xs, xs)
    t = x * theta[0, 0].item() + y * theta[0, 1].item()
    ax.contourf(x, y, t, levels=[t.min() - 1, WATER_T], colors=["tab:blue"], alpha=0.25)
    ax.contour(x, y, t, levels=edges[::2], colors="tab:blue", linewidths=0.3, alpha=0.6)
    ax.contour(x, y, t, levels=[WATER_T], colors="tab:blue", linewidths=1.5)
    ax.annotate("", xy=(35 * theta[0, 0].item(), 35 * theta[0, 1].item()), xytext=(0, 0),
                arrowprops={"arrowstyle": "->", "color": "tab:red"})
    ax.text(36 * theta[0, 0].item(), 36 * theta[0, 1].item(), "up", color="tab:red", fontsize=8)
    ax.set(title="object, slabs and water line", xlabel="x (mm)", ylabel="y (mm)")
    ax.title.set_fontsize(10)

    under = centres < WATER_T
    bx.bar(centres, profile, width=edges[1] - edges[0], color=np.where(under, "tab:blue", "lightgrey"),
           edgecolor="white", linewidth=0.4)
    bx.axvline(WATER_T, color="tab:blue", linewidth=1.5)
    bx.set(title="its dip profile: the area of each slab", xlabel="height t along the dip direction (mm)",
           ylabel="slab area (mm$^2$)")
    bx.title.set_fontsize(10)
    bx.text(WATER_T + 1, profile.max() * 0.95, "under water so far", color="tab:blue", fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
