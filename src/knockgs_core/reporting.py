"""Tables (CSV + Markdown) and figures from per-method evaluation rows.

Statistics are over targets only (mean and sample standard deviation, ddof = 1); frames and
particles are never treated as replicates.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from .io import atomic_write, write_text

__all__ = [
    "main_table",
    "targetwise_table",
    "objects_table",
    "render_table",
    "write_table",
    "to_markdown",
    "plot_main",
    "plot_objects",
    "plot_boundaries",
    "qualitative_figure",
    "comparison_gif",
    "save_figure",
    "CURVE_METRICS",
    "sample_sd",
]

CURVE_METRICS = ("curve_rmse", "peak_abs_diff", "auc_abs_diff", "final_abs_diff")


def sample_sd(x) -> float:
    """Sample standard deviation (ddof = 1) of ``x``; 0 for a single value."""
    x = np.asarray(x, dtype=float)
    return float(np.std(x, ddof=1)) if len(x) > 1 else 0.0


_sd = sample_sd


def main_table(evals: pd.DataFrame, methods: Sequence[str], probes: Sequence[str]) -> pd.DataFrame:
    """One row per method: mean +- sd joint error over targets, mean trajectory RMSE per
    probe (+ sd), mean curve metrics per probe. ``evals`` has a ``method`` column and the
    rows of :func:`knockgs_core.experiments.evaluate_method`."""
    rows = []
    for m in methods:
        e = evals[evals["method"] == m]
        if e.empty:
            continue
        per_target = e.drop_duplicates("target")
        row = {"method": m, "joint_error_pct": per_target["joint_error_pct"].mean(),
               "joint_error_sd": _sd(per_target["joint_error_pct"]), "n_targets": len(per_target)}
        for p in probes:
            ep = e[e["probe"] == p]
            row[f"traj_rmse_{p}"] = ep["traj_rmse"].mean()
            row[f"traj_rmse_{p}_sd"] = _sd(ep["traj_rmse"])
        for p in probes:
            ep = e[e["probe"] == p]
            for c in CURVE_METRICS:
                row[f"{c}_{p}"] = ep[c].mean()
        rows.append(row)
    return pd.DataFrame(rows)


def targetwise_table(evals: pd.DataFrame, methods: Sequence[str], probes: Sequence[str]) -> pd.DataFrame:
    """Every target x method: estimate, joint error, trajectory RMSE per probe."""
    rows = []
    for (target, m), e in evals.groupby(["target", "method"], sort=False):
        first = e.iloc[0]
        row = {"target": target, "method": m, "E_true": first.E_true, "rho_true": first.rho_true,
               "E_hat": first.E_hat, "rho_hat": first.rho_hat, "joint_error_pct": first.joint_error_pct}
        for p in probes:
            row[f"traj_rmse_{p}"] = float(e.loc[e["probe"] == p, "traj_rmse"].mean())
        rows.append(row)
    df = pd.DataFrame(rows)
    order = {m: i for i, m in enumerate(methods)}
    return df.sort_values(["target", "method"], key=lambda s: s.map(order) if s.name == "method" else s).reset_index(drop=True)


def objects_table(
    mains: dict[str, pd.DataFrame], heldout: dict[str, Sequence[str]], calibration_probes: dict[str, str]
) -> pd.DataFrame:
    """Three-object repeatability: per object and method, joint error and the Probe-A and
    (first) Probe-B trajectory RMSE."""
    rows = []
    for obj, t in mains.items():
        pb = heldout[obj][0]
        for r in t.itertuples(index=False):
            d = r._asdict()
            rows.append({"object": obj, "method": d["method"], "joint_error_pct": d["joint_error_pct"],
                         "joint_error_sd": d["joint_error_sd"], "traj_rmse_A": d[f"traj_rmse_{calibration_probes[obj]}"],
                         "probe_B": pb, "traj_rmse_B": d[f"traj_rmse_{pb}"]})
    return pd.DataFrame(rows)


def _fmt(v) -> str:
    if isinstance(v, (float, np.floating)):
        if math.isinf(v):
            return "inf"
        if math.isnan(v):
            return "n/a"
        return f"{v:.4g}"
    return str(v)


def to_markdown(df: pd.DataFrame, *, title: str = "", note: str = "") -> str:
    lines = []
    if title:
        lines += [f"# {title}", ""]
    cols = list(df.columns)
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "|".join("---" if df[c].dtype == object else "---:" for c in cols) + "|")
    for r in df.itertuples(index=False):
        lines.append("| " + " | ".join(_fmt(v) for v in r) + " |")
    if note:
        lines += ["", note]
    return "\n".join(lines) + "\n"


def write_table(df: pd.DataFrame, csv_path, md_path=None, *, title: str = "", note: str = "") -> None:
    """Write ``df`` as CSV (floats ``%.8g``, no index) and, with ``md_path``, as a Markdown
    table (:func:`to_markdown`), each file atomically (:mod:`knockgs_core.io`)."""
    write_text(csv_path, df.to_csv(index=False, float_format="%.8g", lineterminator="\n"))
    if md_path is not None:
        write_text(md_path, to_markdown(df, title=title, note=note))


def save_figure(fig, path, *, dpi: int) -> None:
    """Save a Matplotlib figure atomically; the format follows the file extension (PNG default)."""
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    with atomic_write(path, mode="wb") as fh:
        fig.savefig(fh, dpi=dpi, format=fmt)


def plot_main(table: pd.DataFrame, probes: Sequence[str], path, *, title: str = "") -> None:
    """Parameter error bars (mean +- sd over targets) and Probe A/B trajectory RMSE."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    x = np.arange(len(table))
    axes[0].bar(x, table["joint_error_pct"], yerr=table["joint_error_sd"], capsize=3, color="tab:blue")
    axes[0].set_xticks(x, table["method"], rotation=35, ha="right")
    axes[0].set_ylabel("joint parameter error [%]")
    axes[0].set_title("calibration (Probe A)")
    w = 0.8 / max(1, len(probes))
    for i, p in enumerate(probes):
        axes[1].bar(x + (i - (len(probes) - 1) / 2) * w, table[f"traj_rmse_{p}"], width=w, label=p)
    axes[1].set_yscale("log")
    axes[1].set_xticks(x, table["method"], rotation=35, ha="right")
    axes[1].set_ylabel("trajectory RMSE [m]")
    axes[1].set_title("frozen write-back: Probe A and held-out Probe B")
    axes[1].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def plot_objects(table: pd.DataFrame, path) -> None:
    """Joint error per object and method (three-object repeatability)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = list(dict.fromkeys(table["object"]))
    methods = list(dict.fromkeys(table["method"]))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    w = 0.8 / len(methods)
    x = np.arange(len(objects))
    for i, m in enumerate(methods):
        t = table[table["method"] == m].set_index("object").reindex(objects)
        axes[0].bar(x + (i - (len(methods) - 1) / 2) * w, t["joint_error_pct"], width=w, label=m)
        axes[1].bar(x + (i - (len(methods) - 1) / 2) * w, t["traj_rmse_B"], width=w, label=m)
    for ax, lab in zip(axes, ["joint parameter error [%]", "held-out Probe-B trajectory RMSE [m]"]):
        ax.set_xticks(x, objects)
        ax.set_ylabel(lab)
    axes[1].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def plot_boundaries(table: pd.DataFrame, path, *, title: str = "") -> None:
    """Calibration boundaries (the paper's bar style): one bar per (condition, library) row of
    a boundaries table, the mean joint error over targets [%] with the target maximum as a
    tick; red where the library contract is violated, green where it is preserved or rebuilt."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.85 * len(table) + 2), 4))
    x = np.arange(len(table))
    ok = table["contract_preserved"].astype(bool).to_numpy()
    mean = table["joint_error_mean_pct"].to_numpy(dtype=float)
    ax.bar(x, mean, color=np.where(ok, "tab:green", "tab:red"))
    ax.plot(x, table["joint_error_max_pct"], "k_", markersize=14, label="max over targets")
    for xi, v in zip(x, mean):
        ax.annotate(f"{v:.2f}", (xi, v), ha="center", va="bottom", fontsize=7, xytext=(0, 2), textcoords="offset points")
    labels = [f"{c}\n({lib})" for c, lib in zip(table["condition"], table["library"])]
    ax.set_xticks(x, labels, rotation=35, ha="right", fontsize=8)
    ax.set_ylabel("joint parameter error [%]")
    handles = [plt.Rectangle((0, 0), 1, 1, color="tab:red"), plt.Rectangle((0, 0), 1, 1, color="tab:green"),
               ax.get_lines()[0]]
    ax.legend(handles, ["violates the library contract", "preserves or rebuilds it", "max over targets"], fontsize=7)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def render_table(rows: pd.DataFrame, methods: Sequence[str], probes: Sequence[str]) -> pd.DataFrame:
    """One row per method: ``psnr_fg_{probe}`` and ``ssim_crop_{probe}``, means over targets
    (an infinite PSNR, identical frames, is kept as inf)."""
    out = []
    for m in methods:
        r = rows[rows["method"] == m]
        if r.empty:
            continue
        row = {"method": m}
        for p in probes:
            row[f"psnr_fg_{p}"] = float(r.loc[r["probe"] == p, "psnr_fg"].mean())
        for p in probes:
            row[f"ssim_crop_{p}"] = float(r.loc[r["probe"] == p, "ssim_crop"].mean())
        out.append(row)
    return pd.DataFrame(out)


def _moving_crop(alphas: Sequence[np.ndarray], rgbs: Sequence[np.ndarray], pad: int = 6) -> tuple[slice, slice]:
    """Bounding box of pixels that change over time in any sequence, or of the foreground."""
    moving = np.zeros(alphas[0].shape[1:], dtype=bool)
    for a, c in zip(alphas, rgbs):
        moving |= np.abs(c - c[0]).max(axis=(0, 3)) > 2e-3
    if not moving.any():
        moving = np.any([a.max(0) > 0.5 for a in alphas], axis=0)
    ys, xs = np.nonzero(moving)
    H, W = moving.shape
    if len(ys) == 0:
        return slice(0, H), slice(0, W)
    return slice(max(0, ys.min() - pad), min(H, ys.max() + pad + 1)), slice(max(0, xs.min() - pad), min(W, xs.max() + pad + 1))


def qualitative_figure(
    names: Sequence[str], rgbs: Sequence[np.ndarray], alphas: Sequence[np.ndarray], path, *, title: str = ""
) -> None:
    """Mid and final frame per method (row 1-2) and the final-frame absolute RGB error to
    the target (row 3) on one shared scale clipped at the 99.9th percentile; cropped to the
    moving region. ``names[0]`` is the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ys, xs = _moving_crop(alphas, rgbs)
    T = rgbs[0].shape[0]
    errs = [np.abs(r[-1] - rgbs[0][-1]).mean(-1)[ys, xs] for r in rgbs]
    vmax = float(np.percentile(np.concatenate([e.ravel() for e in errs[1:]]), 99.9)) if len(errs) > 1 else 1.0
    vmax = max(vmax, 1e-6)
    n = len(names)
    fig, axes = plt.subplots(3, n, figsize=(2.2 * n, 6.6), squeeze=False)
    for j, (name, rgb) in enumerate(zip(names, rgbs)):
        axes[0, j].imshow(np.clip(rgb[T // 2][ys, xs], 0, 1))
        axes[1, j].imshow(np.clip(rgb[-1][ys, xs], 0, 1))
        im = axes[2, j].imshow(np.clip(errs[j], 0, vmax), cmap="magma", vmin=0, vmax=vmax)
        axes[0, j].set_title(name, fontsize=8)
        for i in range(3):
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
    axes[0, 0].set_ylabel(f"frame {T // 2}")
    axes[1, 0].set_ylabel(f"frame {T - 1}")
    axes[2, 0].set_ylabel("|RGB error|")
    fig.colorbar(im, ax=axes[2, :].tolist(), shrink=0.8, label=f"final-frame |error| (clipped at 99.9th pct = {vmax:.2g})")
    if title:
        fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def comparison_gif(names: Sequence[str], rgbs: Sequence[np.ndarray], path, *, duration_ms: int = 80, upscale: int = 2) -> None:
    """Side-by-side animation (one panel per sequence, labelled), as an animated GIF.
    Displacements are small, so a bottom strip also shows |frame - target frame| x 20."""
    from PIL import Image, ImageDraw

    T = rgbs[0].shape[0]
    frames = []
    for t in range(T):
        tops = [np.clip(r[t], 0, 1) for r in rgbs]
        bottoms = [np.clip(np.abs(r[t] - rgbs[0][t]) * 20.0, 0, 1) for r in rgbs]
        img = np.concatenate([np.concatenate(tops, axis=1), np.concatenate(bottoms, axis=1)], axis=0)
        im = Image.fromarray((img * 255).astype(np.uint8)).resize((img.shape[1] * upscale, img.shape[0] * upscale), Image.NEAREST)
        draw = ImageDraw.Draw(im)
        w = rgbs[0].shape[2] * upscale
        for j, name in enumerate(names):
            draw.text((j * w + 4, 4), name, fill=(0, 0, 0))
        draw.text((4, im.height - 14), f"frame {t}", fill=(255, 255, 255))
        frames.append(im)
    with atomic_write(path, mode="wb") as fh:
        frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:], duration=duration_ms, loop=0)
