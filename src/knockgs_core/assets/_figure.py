"""Figure of an asset's particles: GS vs fill, and the static support (private)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from knockgs_core.io import atomic_write


def asset_figure(built, path: str | os.PathLike, *, title: str = "", max_points: int = 60000,
                 removed_means=None, supports=(), probes=(), camera_image=None) -> None:
    """Three orthographic views (x-z, y-z, x-y) of GS particles (coloured by their
    Gaussian's colour), fill particles (red) and static support Gaussians (grey).

    Optional layers: ``removed_means`` [M, 3] (Gaussians the contract's filters removed,
    normalized domain: pale blue crosses), ``supports`` (held boxes,
    :class:`~knockgs_core.sim.Box`: black outlines), ``probes`` ((name, force [3], box or
    None) triples: an arrow of the force's direction from the box, or from the body's
    centre for a global probe, and the box in magenta), and ``camera_image`` [H, W, 3] in
    [0, 1] (a fourth panel, the contract camera's view).
    """
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
    from matplotlib.patches import Rectangle

    panels = 3 + (camera_image is not None)
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 5.2))
    removed = np.zeros((0, 3)) if removed_means is None else np.asarray(removed_means, np.float64)
    if len(removed) > max_points:
        removed = removed[np.sort(rng.choice(len(removed), max_points, replace=False))]
    centre = ps.positions[:ps.n_gs].mean(axis=0) if ps.n_gs else np.ones(3)
    for ax, (i, j, lab) in zip(axes, [(0, 2, "x-z"), (1, 2, "y-z"), (0, 1, "x-y")]):
        if len(removed):
            ax.scatter(removed[:, i], removed[:, j], s=4, c="tab:blue", marker="x", lw=0.4, alpha=0.5,
                       label=f"removed Gaussians ({0 if removed_means is None else len(removed_means)})")
        ax.scatter(g.means[static_rows, i], g.means[static_rows, j], s=1, c="0.75", lw=0,
                   label=f"static support ({int(built.static_mask.sum())})")
        ax.scatter(ps.positions[gs_rows, i], ps.positions[gs_rows, j], s=2, c=colors, lw=0,
                   label=f"GS particles ({ps.n_gs})")
        ax.scatter(ps.positions[fill_rows, i], ps.positions[fill_rows, j], s=2, c="tab:red", lw=0,
                   label=f"fill particles ({ps.n_fill}, {ps.fill_cells} cells)")
        for k, box in enumerate(supports):
            c, h = np.asarray(box.center), np.asarray(box.half_size)
            ax.add_patch(Rectangle((c[i] - h[i], c[j] - h[j]), 2 * h[i], 2 * h[j], fill=False, ec="k", lw=1.2,
                                   label="support (held)" if k == 0 else None))
        for k, (name, force, box) in enumerate(probes):
            f = np.asarray(force, np.float64)
            start = centre if box is None else np.asarray(box.center)
            if box is not None:
                c, h = np.asarray(box.center), np.asarray(box.half_size)
                ax.add_patch(Rectangle((c[i] - h[i], c[j] - h[j]), 2 * h[i], 2 * h[j], fill=False, ec="m", lw=1))
            if np.hypot(f[i], f[j]) > 0:
                d = 0.25 * np.array([f[i], f[j]]) / np.linalg.norm(f)
                ax.annotate(name, xy=(start[i] + d[0], start[j] + d[1]), xytext=(start[i], start[j]), fontsize=7,
                            color="m", arrowprops={"arrowstyle": "->", "color": "m"})
        if removed_means is not None:  # the domain: removed floaters may lie far outside it
            ax.set_xlim(0.0, 2.0)
            ax.set_ylim(0.0, 2.0)
        ax.set_aspect("equal")
        ax.set_title(lab)
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
    axes[0].legend(loc="lower left", fontsize=8, markerscale=4)
    if camera_image is not None:
        axes[3].imshow(np.clip(np.asarray(camera_image), 0, 1))
        axes[3].set_title("contract camera")
        axes[3].axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    with atomic_write(path, mode="wb") as fh:
        fig.savefig(fh, dpi=100, format=fmt)
    plt.close(fig)
