"""Hyper-parameters of the estimators: validation, and the candidate-only leave-one-out they are
selected by.

``k`` (neighbour count) and ``alpha`` (ridge strength) take a fixed value or ``"cv"``: then
:func:`~knockgs_core.calibration.select_knn_k` (in ``_neighbors``, beside the KNN estimator) /
:func:`~knockgs_core.calibration.select_ridge_alpha` (in ``_ridge``, beside the ridge
estimators) choose them at ``fit`` from the grids :data:`DEFAULT_KS` / :data:`DEFAULT_ALPHAS`,
holding out one candidate at a time (each fold refits the standardizer; :func:`_loo_errors`,
:func:`_selection_table` here). Only candidates are used; queries and targets never are.
"""

from __future__ import annotations

import math

import numpy as np

from ._estimate import joint_error_pct
from ._standardize import _as_matrix

__all__ = ["DEFAULT_KS", "DEFAULT_ALPHAS"]

DEFAULT_KS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 8, 10)
DEFAULT_ALPHAS: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)


def _check_k(k, *, allow_cv: bool, name: str = "k") -> int | str:
    if allow_cv and k == "cv":
        return "cv"
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or k < 1:
        allowed = "a positive integer or 'cv'" if allow_cv else "a positive integer"
        raise ValueError(f"{name} must be {allowed}, got {k!r}")
    return int(k)


def _check_alpha(alpha, *, allow_cv: bool = True, name: str = "alpha") -> float | str:
    if allow_cv and alpha == "cv":
        return "cv"
    if (
        isinstance(alpha, (bool, np.bool_))
        or not isinstance(alpha, (int, float, np.integer, np.floating))
        or not math.isfinite(alpha)
        or alpha < 0
    ):
        allowed = "a finite number >= 0 or 'cv'" if allow_cv else "a finite number >= 0"
        raise ValueError(f"{name} must be {allowed}, got {alpha!r}")
    return float(alpha)


def _selection_label(value) -> str:
    """``"cv"`` for a value selected by leave-one-out, else ``"fixed"``."""
    return "cv" if value == "cv" else "fixed"


def _loo_errors(make, features, theta, names) -> tuple[np.ndarray, int]:
    """Leave-one-candidate-out joint errors; each fold refits the standardizer.

    Returns per-candidate errors and the number of local-ridge fallbacks.
    """
    x = _as_matrix(features, "features")
    theta = np.asarray(theta, dtype=float)
    names = [str(n) for n in names]
    n = x.shape[0]
    errors = np.empty(n)
    fallbacks = 0
    for i in range(n):
        keep = [j for j in range(n) if j != i]
        est = make().fit(x[keep], theta[keep], [names[j] for j in keep])
        (pred,) = est.predict(x[i : i + 1], names=[names[i]])
        errors[i] = joint_error_pct(pred.theta, theta[i])
        fallbacks += bool(pred.details.get("fallback", False))
    return errors, fallbacks


def _selection_table(column, values, runs):
    import pandas as pd

    rows = []
    for value, (errors, fallbacks) in zip(values, runs):
        rows.append(
            {
                column: value,
                "mean_joint_error_pct": float(errors.mean()),
                "max_joint_error_pct": float(errors.max()),
                "n_folds": int(errors.size),
                "n_fallbacks": int(fallbacks),
            }
        )
    table = pd.DataFrame(rows)
    best = int(np.argmin(table["mean_joint_error_pct"].to_numpy()))  # first of equal minima
    table["selected"] = np.arange(len(table)) == best
    return values[best], table
