"""Descriptor identifiability: which candidates the 5-D descriptor cannot tell apart.

The paper's section on discretization, object and identifiability boundaries, from the
frozen descriptor tables and the library's Probe-A rollouts:

- every candidate pair (54 candidates: 1,431 pairs): the standardized descriptor distance
  (features standardized on the candidates, as every estimator sees them), the parameter
  distance ``sqrt(dlog s_E^2 + dlog s_rho^2)``, and the full-trajectory RMSE between the two
  candidates' Probe-A rollouts [m] (all particles and frames). A pair is *close in
  descriptor but far in parameters* when its descriptor distance is in the lowest
  ``close_quantile`` of all pairs and its parameter distance above the median; such a pair is
  an ambiguity *added by the compression* when its trajectories are also far apart (RMSE
  above the median of all pairs): the rollouts differ, the descriptors do not;
- the condition numbers of the local-ridge design (the frozen k and alpha) at every
  candidate (leave-one-out: the library without it, its descriptor as the query) and at
  every target: the centred k x 5 neighbourhood design, alone and augmented with
  ``sqrt(alpha) I`` (what the solve sees).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

from ..calibration import LocalRidge, Standardizer
from ..calibration._tables import library_arrays, query_arrays

__all__ = ["pair_table", "condition_table", "identifiability_summary", "plot_identifiability"]


def pair_table(library: pd.DataFrame, rollouts: Mapping[str, object] | None = None, *,
               close_quantile: float = 0.1, max_particles: int = 20_000) -> pd.DataFrame:
    """One row per candidate pair (``a < b`` in library order): ``descriptor_distance``,
    ``parameter_distance``, ``traj_rmse`` [m] (NaN without ``rollouts``: candidate name ->
    rollout path or positions [T, N, 3]; over at most ``max_particles`` particles, evenly
    strided, and every frame), and the flags ``close_far`` and ``compression_ambiguity``
    (module docs)."""
    names, theta, features = library_arrays(library, "library table")
    z = Standardizer().fit_transform(features)
    logt = np.log(theta)
    n = len(names)
    ia, ib = np.triu_indices(n, k=1)
    dz = np.linalg.norm(z[ia] - z[ib], axis=1)
    dp = np.linalg.norm(logt[ia] - logt[ib], axis=1)
    rmse = np.full(len(ia), np.nan)
    if rollouts is not None:
        X = _positions(names, rollouts, max_particles)
        for m, (a, b) in enumerate(zip(ia, ib)):
            d = X[a] - X[b]
            rmse[m] = float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))
    out = pd.DataFrame({"a": [names[i] for i in ia], "b": [names[i] for i in ib],
                        "descriptor_distance": dz, "parameter_distance": dp, "traj_rmse": rmse})
    close = dz <= np.quantile(dz, close_quantile)
    far = dp > np.median(dp)
    out["close_far"] = close & far
    out["compression_ambiguity"] = out["close_far"] & (rmse > np.nanmedian(rmse)) if rollouts is not None else False
    out.attrs["close_quantile"] = close_quantile
    return out


def _positions(names, rollouts, max_particles: int) -> list[np.ndarray]:
    from ..rollout import read_rollout

    X = []
    for name in names:
        if name not in rollouts:
            raise ValueError(f"no Probe-A rollout for candidate {name!r}")
        item = rollouts[name]
        x = np.asarray(item if isinstance(item, np.ndarray) else read_rollout(item).positions)
        keep = np.unique(np.linspace(0, x.shape[1] - 1, min(x.shape[1], max_particles)).astype(int))
        X.append(np.asarray(x[:, keep], dtype=np.float64))
    shapes = {x.shape for x in X}
    if len(shapes) != 1:
        raise ValueError(f"the candidates' rollouts differ in shape: {sorted(shapes)[:3]}")
    return X


def condition_table(library: pd.DataFrame, queries: pd.DataFrame, *, k: int = 10, alpha: float = 1e-3) -> pd.DataFrame:
    """One row per candidate (``role`` candidate_loo) and per query (``role`` target): the
    local-ridge neighbourhood design's condition numbers (``condition_number`` augmented with
    sqrt(alpha) I, ``condition_number_unregularized``) and whether it fell back to KNN."""
    names, theta, features = library_arrays(library, "library table")
    q_names, q_features = query_arrays(queries, "query table", names)
    rows = []

    def record(role, name, est):
        d = est.details
        rows.append({"role": role, "case_name": name, "condition_number": d.get("condition_number"),
                     "condition_number_unregularized": d.get("condition_number_unregularized"),
                     "fallback": bool(d.get("fallback"))})

    n = len(names)
    for i in range(n):
        keep = [j for j in range(n) if j != i]
        lr = LocalRidge(k=k, alpha=alpha, uncertainty=False).fit(features[keep], theta[keep], [names[j] for j in keep])
        record("candidate_loo", names[i], lr.predict(features[i:i + 1], names=[f"loo_{names[i]}"])[0])
    lr = LocalRidge(k=k, alpha=alpha, uncertainty=False).fit(features, theta, names)
    for name, est in zip(q_names, lr.predict(q_features, names=q_names)):
        record("target", name, est)
    out = pd.DataFrame(rows)
    for c in ("condition_number", "condition_number_unregularized"):
        out[c] = pd.to_numeric(out[c], errors="coerce")
    return out


def identifiability_summary(pairs: pd.DataFrame, cond: pd.DataFrame) -> pd.DataFrame:
    """The reported table: one row per quantity (``quantity``, ``value``). Close pairs: the
    descriptor distance in the lowest ``close_quantile`` of all pairs (:func:`pair_table`),
    far: parameter distance above the median; trajectories far apart: RMSE above the median."""
    from scipy.stats import spearmanr

    rows = [("candidate pairs", len(pairs)),
            ("Spearman(descriptor distance, parameter distance)",
             float(spearmanr(pairs["descriptor_distance"], pairs["parameter_distance"]).statistic)),
            ("pairs close in descriptor, far in parameters", int(pairs["close_far"].sum()))]
    close = pairs["descriptor_distance"] <= pairs["descriptor_distance"].quantile(pairs.attrs.get("close_quantile", 0.1))
    worst = float(pairs.loc[close, "parameter_distance"].max())
    rows += [("largest parameter distance among the close pairs", worst),
             ("its percentile among all pairs' parameter distances", float(100.0 * (pairs["parameter_distance"] < worst).mean()))]
    if pairs["traj_rmse"].notna().all():
        rows += [("Spearman(trajectory RMSE, parameter distance)",
                  float(spearmanr(pairs["traj_rmse"], pairs["parameter_distance"]).statistic)),
                 ("Spearman(descriptor distance, trajectory RMSE)",
                  float(spearmanr(pairs["descriptor_distance"], pairs["traj_rmse"]).statistic)),
                 ("of those, with trajectories far apart (ambiguity added by the descriptor)",
                  int(pairs["compression_ambiguity"].sum()))]
    for role, label in (("candidate_loo", "candidates (leave-one-out)"), ("target", "targets")):
        c = cond[cond["role"] == role]
        for col, what in (("condition_number_unregularized", "design"), ("condition_number", "design + sqrt(alpha) I")):
            v = c[col].dropna()
            rows.append((f"condition number, {label}, {what}: median", float(v.median()) if len(v) else float("nan")))
            rows.append((f"condition number, {label}, {what}: max", float(v.max()) if len(v) else float("nan")))
        rows.append((f"local-ridge fallbacks, {label}", int(c["fallback"].sum())))
    return pd.DataFrame(rows, columns=["quantity", "value"])


def plot_identifiability(pairs: pd.DataFrame, cond: pd.DataFrame, path, *, title: str = "") -> None:
    """Two panels: descriptor vs parameter distance of every pair (colour: trajectory RMSE;
    flagged pairs circled), and the condition numbers of candidates and targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..reporting import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    colour = pairs["traj_rmse"] if pairs["traj_rmse"].notna().all() else None
    sc = ax.scatter(pairs["parameter_distance"], pairs["descriptor_distance"], c=colour, s=6, cmap="viridis")
    f = pairs[pairs["close_far"]]
    ax.scatter(f["parameter_distance"], f["descriptor_distance"], s=40, facecolors="none", edgecolors="r",
               label="close in descriptor, far in parameters")
    if colour is not None:
        fig.colorbar(sc, ax=ax, label="trajectory RMSE [m]")
    ax.set_xlabel("parameter distance (log scales)")
    ax.set_ylabel("standardized descriptor distance")
    ax.legend(fontsize=7)
    ax = axes[1]
    for role, m in (("candidate_loo", "o"), ("target", "s")):
        c = cond[cond["role"] == role]
        ax.scatter(np.arange(len(c)), c["condition_number"], marker=m, s=14, label=role.replace("_", " "))
    ax.set_yscale("log")
    ax.set_xlabel("candidate / target index")
    ax.set_ylabel("condition number (design + sqrt(alpha) I)")
    ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
