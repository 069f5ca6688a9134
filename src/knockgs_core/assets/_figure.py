"""Figure of an asset's particles: GS vs fill, and the static support (private)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from knockgs_core.io import atomic_write


def asset_figure(built, path: str | os.PathLike, *, title: str = "", max_points: int = 60000) -> None:
    """Three orthographic views (x-z, y-z, x-y) of GS particles (coloured by their
    Gaussian's colour), fill particles (red) and static support Gaussians (grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ps = built.particles
    g = built.gaussians
    rng = np.random.default_rng(0)

    def thin(idx):
        return idx if len(idx) <= max_points else np.sort(rng.choice(idx, max_points, replace=False))

    gs_rows = thin(np.arange(ps.n_gs))
    fill_rows = thin(np.arange(ps.n_gs, len(ps)))
    static_rows = thin(np.flatnonzero(built.static_mask))
    colors = g.colors()[ps.gaussian_index[gs_rows]]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2))
    for ax, (i, j, lab) in zip(axes, [(0, 2, "x-z"), (1, 2, "y-z"), (0, 1, "x-y")]):
        ax.scatter(g.means[static_rows, i], g.means[static_rows, j], s=1, c="0.75", lw=0,
                   label=f"static support ({int(built.static_mask.sum())})")
        ax.scatter(ps.positions[gs_rows, i], ps.positions[gs_rows, j], s=2, c=colors, lw=0,
                   label=f"GS particles ({ps.n_gs})")
        ax.scatter(ps.positions[fill_rows, i], ps.positions[fill_rows, j], s=2, c="tab:red", lw=0,
                   label=f"fill particles ({ps.n_fill}, {ps.fill_cells} cells)")
        ax.set_aspect("equal")
        ax.set_title(lab)
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
    axes[0].legend(loc="lower left", fontsize=8, markerscale=4)
    fig.suptitle(title)
    fig.tight_layout()
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    with atomic_write(path, mode="wb") as fh:
        fig.savefig(fh, dpi=100, format=fmt)
    plt.close(fig)
