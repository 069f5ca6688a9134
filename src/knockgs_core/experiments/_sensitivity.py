"""Offline estimator sensitivity: library size and the (k, alpha) grid of local ridge.

The paper's appendix "Offline estimator sensitivity", computed from the frozen descriptor
tables alone (no new rollout):

- *Library size*: ``draws`` predeclared random orders of the candidates (numpy
  ``default_rng(seed)``); the subset of size s of a draw is its first s candidates, so the
  subsets of one draw are nested. Local ridge at the frozen configuration fitted on each
  subset predicts the split's targets from their Probe-A descriptors; the five-target mean
  joint error per subset, and its mean and sd over the draws per size. The full library is
  the last row; the full-library response KNN (its k by candidate-only leave-one-out, as in
  the main table) is the reference line.
- *(k, alpha) grid*: for every pair, the candidate-only leave-one-out mean joint error (each
  candidate predicted from the others, the standardizer refitted per fold) and the held-out
  mean joint error on the split's targets. The held-out column is a post-hoc diagnostic:
  the reported configuration is the frozen one (config ``method_params.local_ridge``), never
  chosen from this grid; :func:`k_alpha_grid` records which cell the leave-one-out alone
  would pick.

Every prediction is counted: fallbacks (local ridge's KNN fallback) and non-finite values
are reported with the tables (:func:`prediction_counts`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..calibration import LocalRidge, ResponseKNN, joint_error_pct
from ..calibration._tables import library_arrays, query_arrays

__all__ = [
    "SensitivitySettings",
    "nested_subsets",
    "size_sensitivity",
    "size_summary",
    "k_alpha_grid",
    "knn_reference",
    "prediction_counts",
    "plot_sensitivity",
]


@dataclass(frozen=True)
class SensitivitySettings:
    """The predeclared design: subset ``sizes`` (candidates), ``draws`` per size, the draws'
    ``seed``; the frozen local-ridge configuration (``k``, ``alpha``); the grid ``ks`` x
    ``alphas``."""

    sizes: tuple[int, ...] = (18, 27, 36, 45)
    draws: int = 30
    seed: int = 20260201
    k: int = 10
    alpha: float = 1e-3
    ks: tuple[int, ...] = (4, 6, 8, 10, 12, 15)
    alphas: tuple[float, ...] = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1)

    def __post_init__(self):
        if self.draws < 1 or not self.sizes or min(self.sizes) < 1:
            raise ValueError("sizes must be positive and draws >= 1")
        if list(self.sizes) != sorted(set(self.sizes)):
            raise ValueError("sizes must be strictly increasing")


def nested_subsets(names: Sequence[str], sizes: Sequence[int], draws: int, seed: int) -> list[dict[int, list[str]]]:
    """``draws`` nested subsets of ``names``: for each draw a random order of the names
    (``default_rng(seed)``, one permutation per draw in turn); size s takes its first s.
    Returns, per draw, size -> names (in library order)."""
    names = list(names)
    if max(sizes) > len(names):
        raise ValueError(f"subset size {max(sizes)} exceeds the library's {len(names)} candidates")
    rank = {n: i for i, n in enumerate(names)}
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(draws):
        order = rng.permutation(len(names))
        out.append({int(s): sorted((names[i] for i in order[:s]), key=rank.__getitem__) for s in sizes})
    return out


def _targets_theta(targets: pd.DataFrame, q_names: Sequence[str]) -> np.ndarray:
    t = targets.set_index("case_name")
    missing = [n for n in q_names if n not in t.index]
    if missing:
        raise ValueError(f"targets lack the queries {missing[:5]}")
    return t.loc[list(q_names), ["E_scale", "density_scale"]].to_numpy(dtype=float)


def _predict(estimator, features, theta, names, q_features, q_names) -> tuple[np.ndarray, int]:
    """Fit ``estimator`` on the library rows and predict the queries: ([n, 2], fallbacks)."""
    estimator.fit(features, theta, list(names))
    est = estimator.predict(q_features, names=list(q_names))
    pred = np.array([e.theta for e in est], dtype=float)
    fallbacks = sum(bool(e.details.get("fallback")) for e in est)
    return pred, fallbacks


def size_sensitivity(library: pd.DataFrame, queries: pd.DataFrame, targets: pd.DataFrame,
                     settings: SensitivitySettings = SensitivitySettings()) -> pd.DataFrame:
    """One row per (size, draw) and one for the full library: local ridge at the frozen
    (k, alpha) fitted on the subset, the targets' mean joint error [%] and its counts.
    ``targets`` holds the queries' labels (``case_name, E_scale, density_scale``); they
    only score the predictions."""
    names, theta, features = library_arrays(library, "library table")
    q_names, q_features = query_arrays(queries, "query table", names)
    truth = _targets_theta(targets, q_names)
    index = {n: i for i, n in enumerate(names)}
    rows = []
    draws = nested_subsets(names, settings.sizes, settings.draws, settings.seed)
    for d, subsets in enumerate(draws):
        for size, subset in subsets.items():
            idx = [index[n] for n in subset]
            pred, fb = _predict(LocalRidge(k=settings.k, alpha=settings.alpha, uncertainty=False), features[idx], theta[idx],
                                subset, q_features, q_names)
            err = joint_error_pct(pred, truth)
            rows.append({"size": size, "draw": d, "mean_joint_error_pct": float(np.mean(err)), "n_predictions": len(err),
                         "n_fallback": fb, "n_nonfinite": int(np.sum(~np.isfinite(pred).all(axis=1)))})
    pred, fb = _predict(LocalRidge(k=settings.k, alpha=settings.alpha, uncertainty=False), features, theta, names,
                        q_features, q_names)
    err = joint_error_pct(pred, truth)
    rows.append({"size": len(names), "draw": -1, "mean_joint_error_pct": float(np.mean(err)), "n_predictions": len(err),
                 "n_fallback": fb, "n_nonfinite": int(np.sum(~np.isfinite(pred).all(axis=1)))})
    return pd.DataFrame(rows)


def knn_reference(library: pd.DataFrame, queries: pd.DataFrame, targets: pd.DataFrame, **options) -> tuple[float, int]:
    """The full-library response KNN's targets mean joint error [%] with the main table's
    ``options`` (there ``k="cv"``: k by candidate-only leave-one-out) and the k it used."""
    names, theta, features = library_arrays(library, "library table")
    q_names, q_features = query_arrays(queries, "query table", names)
    knn = ResponseKNN(**options)
    pred, _ = _predict(knn, features, theta, names, q_features, q_names)
    return float(np.mean(joint_error_pct(pred, _targets_theta(targets, q_names)))), int(knn.effective_params()["k"])


def size_summary(rows: pd.DataFrame, *, knn_pct: float) -> pd.DataFrame:
    """Per library size: mean and sd (ddof 1) over the draws of the mean joint error [%],
    the draws, predictions, fallbacks and non-finite values; the KNN reference in every row."""
    out = []
    for size, g in rows.groupby("size", sort=True):
        e = g["mean_joint_error_pct"].to_numpy()
        out.append({"size": int(size), "draws": len(g), "mean_joint_error_pct": float(e.mean()),
                    "sd_joint_error_pct": float(e.std(ddof=1)) if len(e) > 1 else 0.0,
                    "min_pct": float(e.min()), "max_pct": float(e.max()), "n_predictions": int(g["n_predictions"].sum()),
                    "n_fallback": int(g["n_fallback"].sum()), "n_nonfinite": int(g["n_nonfinite"].sum()),
                    "knn_full_pct": knn_pct})
    return pd.DataFrame(out)


def k_alpha_grid(library: pd.DataFrame, queries: pd.DataFrame, targets: pd.DataFrame,
                 settings: SensitivitySettings = SensitivitySettings()) -> pd.DataFrame:
    """One row per (k, alpha): candidate-only leave-one-out mean joint error [%] over all
    candidates, the held-out mean joint error [%] on the targets (post-hoc diagnostic), their
    prediction, fallback and non-finite counts, ``frozen`` (the configuration reported) and
    ``loo_best`` (the cell the leave-one-out alone would pick; held-out labels play no part)."""
    names, theta, features = library_arrays(library, "library table")
    q_names, q_features = query_arrays(queries, "query table", names)
    truth = _targets_theta(targets, q_names)
    n = len(names)
    rows = []
    for k in settings.ks:
        for alpha in settings.alphas:
            loo_err, fb_loo, nf_loo = [], 0, 0
            for i in range(n):
                keep = [j for j in range(n) if j != i]
                pred, fb = _predict(LocalRidge(k=k, alpha=alpha, uncertainty=False), features[keep], theta[keep],
                                    [names[j] for j in keep], features[i:i + 1], [f"loo_{names[i]}"])
                fb_loo += fb
                nf_loo += int(not np.isfinite(pred).all())
                loo_err.append(float(joint_error_pct(pred[0], theta[i])))
            pred, fb = _predict(LocalRidge(k=k, alpha=alpha, uncertainty=False), features, theta, names, q_features, q_names)
            held = joint_error_pct(pred, truth)
            rows.append({"k": k, "alpha": alpha, "loo_joint_error_pct": float(np.mean(loo_err)),
                         "heldout_joint_error_pct": float(np.mean(held)), "n_predictions": n + len(held),
                         "n_fallback": fb_loo + fb, "n_nonfinite": nf_loo + int(np.sum(~np.isfinite(pred).all(axis=1))),
                         "frozen": bool(k == settings.k and alpha == settings.alpha)})
    out = pd.DataFrame(rows)
    out["loo_best"] = False
    out.loc[out["loo_joint_error_pct"].idxmin(), "loo_best"] = True
    return out


def prediction_counts(size_rows: pd.DataFrame, grid: pd.DataFrame) -> dict:
    """Every offline prediction of the two studies: total, fallbacks, non-finite values."""
    return {"predictions": int(size_rows["n_predictions"].sum() + grid["n_predictions"].sum()),
            "fallbacks": int(size_rows["n_fallback"].sum() + grid["n_fallback"].sum()),
            "nonfinite": int(size_rows["n_nonfinite"].sum() + grid["n_nonfinite"].sum())}


def plot_sensitivity(summary: pd.DataFrame, grid: pd.DataFrame, path, *, title: str = "") -> None:
    """Three panels: the library-size curve (mean +- sd over draws, KNN reference line), and
    heatmaps of the leave-one-out and held-out errors over (k, alpha), the frozen cell boxed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from ..reporting import save_figure

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ax = axes[0]
    ax.errorbar(summary["size"], summary["mean_joint_error_pct"], yerr=summary["sd_joint_error_pct"], marker="o", capsize=3,
                label="local ridge (frozen k, alpha)")
    ax.axhline(float(summary["knn_full_pct"].iloc[0]), color="0.4", ls="--", label="response KNN, full library")
    ax.set_xlabel("library size (candidates)")
    ax.set_ylabel("mean joint error [%]")
    ax.legend(fontsize=8)
    ks, alphas = sorted(grid["k"].unique()), sorted(grid["alpha"].unique())
    for ax, col, name in ((axes[1], "loo_joint_error_pct", "candidate leave-one-out"),
                          (axes[2], "heldout_joint_error_pct", "held-out targets (post hoc)")):
        M = grid.pivot(index="k", columns="alpha", values=col).loc[ks, alphas].to_numpy()
        im = ax.imshow(M, origin="lower", aspect="auto", cmap="viridis")
        ax.set_xticks(range(len(alphas)), [f"{a:g}" for a in alphas], fontsize=7)
        ax.set_yticks(range(len(ks)), [str(k) for k in ks])
        ax.set_xlabel("alpha")
        ax.set_ylabel("k")
        ax.set_title(f"{name} [%]", fontsize=9)
        for i in range(len(ks)):
            for j in range(len(alphas)):
                ax.text(j, i, f"{M[i, j]:.2f}", ha="center", va="center", fontsize=6, color="w")
        fz = grid[grid["frozen"]]
        if not fz.empty:
            i, j = ks.index(int(fz["k"].iloc[0])), alphas.index(float(fz["alpha"].iloc[0]))
            ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, ec="r", lw=2))
        fig.colorbar(im, ax=ax, fraction=0.046)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
