"""Ridge estimators: one global fit over all candidates, and the paper's local ridge (SPEC §6);
the selection of their ridge strength by candidate-only leave-one-out (:func:`select_ridge_alpha`).

Ridge fits centre the data, penalize the slopes only (unregularized intercept) and fit the
two scales independently. Local ridge takes the k nearest candidates with equal weights,
clips its predictions to the candidate min/max of each scale, and falls back to
inverse-distance KNN (k = 5) when fewer than 3 neighbours exist or the solve fails; the
fallback is recorded in the estimate's details.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ._base import LibraryEstimator
from ._estimate import THETA_NAMES
from ._selection import DEFAULT_ALPHAS, _check_alpha, _check_k, _loo_errors, _selection_label, _selection_table

__all__ = ["MIN_RIDGE_NEIGHBOURS", "FALLBACK_K", "GlobalRidge", "LocalRidge", "select_ridge_alpha"]

#: local ridge needs at least this many neighbours, else it falls back to KNN
MIN_RIDGE_NEIGHBOURS = 3
#: k of the inverse-distance KNN fallback of local ridge
FALLBACK_K = 5


@dataclass
class _RidgeFit:
    intercept: np.ndarray  # [q]
    coef: np.ndarray  # [p, q]
    z_mean: np.ndarray  # [p]
    condition_number: float  # of the centred design augmented with sqrt(alpha) I
    condition_number_unregularized: float  # of the centred design alone
    failure: str | None = None

    def predict(self, z: np.ndarray) -> np.ndarray:
        return self.intercept + z @ self.coef


def _ridge_fit(z: np.ndarray, y: np.ndarray, alpha: float) -> _RidgeFit:
    """Ridge with an unregularized intercept: centre, penalize the slopes only.

    Solves ``min_b ||yc - zc b||^2 + alpha ||b||^2`` for every column of y independently,
    via the SVD of the centred design ``zc``: the singular values of the augmented design
    ``[zc; sqrt(alpha) I]`` are ``sqrt(s^2 + alpha)``, whose ratio is the reported
    condition number. A numerically rank-deficient augmented design (possible only with
    alpha = 0) is a failed solve.
    """
    m, p = z.shape
    z_mean = z.mean(axis=0)
    y_mean = y.mean(axis=0)
    zc = z - z_mean
    yc = y - y_mean
    nan = np.full(y.shape[1], np.nan)
    try:
        u, s, vt = np.linalg.svd(zc, full_matrices=False)
    except np.linalg.LinAlgError as exc:
        return _RidgeFit(nan, np.full((p, y.shape[1]), np.nan), z_mean, math.inf, math.inf,
                         f"SVD failed: {exc}")
    s_full = np.zeros(p)
    s_full[: s.size] = s
    aug = np.sqrt(s_full**2 + alpha)
    cond = float(aug.max() / aug.min()) if aug.min() > 0 else math.inf
    cond_raw = float(s_full.max() / s_full.min()) if s_full.min() > 0 else math.inf
    if not aug.max() > 0 or aug.min() <= aug.max() * max(m, p) * np.finfo(float).eps:
        return _RidgeFit(nan, np.full((p, y.shape[1]), np.nan), z_mean, cond, cond_raw,
                         "rank-deficient neighbourhood design (alpha too small)")
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(s**2 + alpha > 0, s / (s**2 + alpha), 0.0)
    coef = vt.T @ (gain[:, None] * (u.T @ yc))
    intercept = y_mean - z_mean @ coef
    if not (np.all(np.isfinite(coef)) and np.all(np.isfinite(intercept))):
        return _RidgeFit(nan, coef, z_mean, cond, cond_raw, "non-finite ridge solution")
    return _RidgeFit(intercept, coef, z_mean, cond, cond_raw)


def _coef_details(fit: _RidgeFit) -> dict:
    return {
        name: {"intercept": float(fit.intercept[j]), "slopes": fit.coef[:, j].tolist()}
        for j, name in enumerate(THETA_NAMES)
    }


class GlobalRidge(LibraryEstimator):
    """Ridge regression of each scale on the standardized descriptor over all candidates.

    Unregularized intercept, alpha on the slopes only, the two scales fitted independently,
    no clipping.

    Parameters
    ----------
    alpha:
        Ridge strength (>= 0), or ``"cv"`` to select it by candidate-only leave-one-out
        (:func:`select_ridge_alpha`) at ``fit``; the authors' Ficus setting is 0.01.
    alphas:
        Grid searched when ``alpha="cv"``.
    """

    method = "global_ridge"

    def __init__(
        self, *, alpha: float | Literal["cv"] = 0.01, alphas: Sequence[float] = DEFAULT_ALPHAS
    ):
        self.alpha = _check_alpha(alpha)
        self.alphas = tuple(_check_alpha(a, allow_cv=False, name="alphas entry") for a in alphas)
        if not self.alphas:
            raise ValueError("alphas must not be empty")

    def _fit_method(self):
        if self.alpha == "cv":
            self.alpha_, self.cv_table_ = select_ridge_alpha(
                self.features_, self.theta_, self.names_, alphas=self.alphas
            )
        else:
            self.alpha_, self.cv_table_ = self.alpha, None
        self.fit_ = _ridge_fit(self.z_, self.theta_, self.alpha_)
        if self.fit_.failure:
            raise ValueError(f"GlobalRidge: {self.fit_.failure}; use alpha > 0")

    def _predict_one(self, z):
        return self.fit_.predict(z), {
            "alpha": self.alpha_,
            "alpha_selection": _selection_label(self.alpha),
            "n_candidates": len(self.names_),
            "condition_number": self.fit_.condition_number,
            "coefficients": _coef_details(self.fit_),
        }

    def effective_params(self) -> dict:
        params = {"alpha": self.alpha_, "alpha_selection": _selection_label(self.alpha)}
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


class LocalRidge(LibraryEstimator):
    """Hard-neighbourhood local ridge, the paper's estimator.

    For each query: the k candidates nearest in standardized descriptor space (ties broken
    by case name), equal weights, a ridge fit of each scale on the centred neighbourhood
    (alpha on the slopes, unregularized intercept), evaluated at the query and clipped to
    the candidate min/max of that scale. With fewer than 3 neighbours, or when the solve
    fails, it falls back to inverse-distance KNN with k = 5 and records why.

    Details per estimate (beyond the paper): neighbour names and distances, the condition
    number of the centred design augmented with ``sqrt(alpha) I`` (and of the centred
    design alone), the unclipped values and per-scale clipped flags, the fallback flag and
    reason, and a per-scale uncertainty: the leave-one-neighbour-out jackknife standard
    error ``sqrt((k-1)/k * sum_j (p_(j) - p_bar)^2)`` of the unclipped prediction, where
    ``p_(j)`` is the prediction of the ridge refit without neighbour j (same alpha, same
    query, recentred). It measures how much the estimate leans on single neighbours; it
    is not a calibrated confidence interval.

    Parameters
    ----------
    k:
        Neighbourhood size (authors: 10); a smaller library uses all candidates.
    alpha:
        Ridge strength on the slopes (>= 0; authors: 1e-3), or ``"cv"`` to select it by
        candidate-only leave-one-out (:func:`select_ridge_alpha` with this k).
    alphas:
        Grid searched when ``alpha="cv"``.
    clip:
        Clip to the candidate bounds (the paper's setting; ``False`` only for ablations).
    uncertainty:
        Compute the jackknife standard errors (k extra small solves per query).
    """

    method = "local_ridge"

    def __init__(
        self,
        *,
        k: int = 10,
        alpha: float | Literal["cv"] = 1e-3,
        alphas: Sequence[float] = DEFAULT_ALPHAS,
        clip: bool = True,
        uncertainty: bool = True,
    ):
        self.k = _check_k(k, allow_cv=False)
        self.alpha = _check_alpha(alpha)
        self.alphas = tuple(_check_alpha(a, allow_cv=False, name="alphas entry") for a in alphas)
        if not self.alphas:
            raise ValueError("alphas must not be empty")
        if not isinstance(clip, bool) or not isinstance(uncertainty, bool):
            raise ValueError("clip and uncertainty must be True or False")
        self.clip = clip
        self.uncertainty = uncertainty

    def _fit_method(self):
        if self.alpha == "cv":
            self.alpha_, self.cv_table_ = select_ridge_alpha(
                self.features_, self.theta_, self.names_, alphas=self.alphas, k=self.k
            )
        else:
            self.alpha_, self.cv_table_ = self.alpha, None

    def _predict_one(self, z):
        idx, d = self._neighbours(z, self.k)
        base = {
            "k": self.k,
            "alpha": self.alpha_,
            "alpha_selection": _selection_label(self.alpha),
        }
        if idx.size < MIN_RIDGE_NEIGHBOURS:
            return self._fallback(
                z, base, f"only {idx.size} neighbours (< {MIN_RIDGE_NEIGHBOURS})"
            )
        fit = _ridge_fit(self.z_[idx], self.theta_[idx], self.alpha_)
        if fit.failure:
            return self._fallback(z, base, f"solve failed: {fit.failure}")
        raw = fit.predict(z)
        if self.clip:
            theta = np.clip(raw, self.theta_min_, self.theta_max_)
        else:
            theta = raw.copy()
        details = dict(base)
        details.update(
            {
                "neighbours": [self.names_[i] for i in idx],
                "distances": d.tolist(),
                "condition_number": fit.condition_number,
                "condition_number_unregularized": fit.condition_number_unregularized,
                "unclipped": dict(zip(THETA_NAMES, raw.tolist())),
                "clipped": {n: bool(theta[j] != raw[j]) for j, n in enumerate(THETA_NAMES)},
                "fallback": False,
                "fallback_reason": None,
                "coefficients": _coef_details(fit),
            }
        )
        if self.uncertainty:
            se, note = self._jackknife(z, idx)
            details["uncertainty"] = dict(zip(THETA_NAMES, se)) if se is not None else None
            details["uncertainty_method"] = "leave-one-neighbour-out jackknife standard error"
            if note:
                details["uncertainty_note"] = note
        return theta, details

    def _jackknife(self, z, idx) -> tuple[list[float] | None, str | None]:
        m = idx.size
        preds = np.empty((m, 2))
        for j in range(m):
            keep = np.delete(idx, j)
            fit = _ridge_fit(self.z_[keep], self.theta_[keep], self.alpha_)
            if fit.failure:
                return None, f"refit without {self.names_[idx[j]]} failed: {fit.failure}"
            preds[j] = fit.predict(z)
        dev = preds - preds.mean(axis=0)
        se = np.sqrt((m - 1) / m * np.sum(dev**2, axis=0))
        return se.tolist(), None

    def _fallback(self, z, base, reason):
        theta, knn = self._knn(z, FALLBACK_K, "distance")
        details = dict(base)
        details.update(knn)
        details["k"] = base["k"]
        details["fallback_k"] = FALLBACK_K
        details.update(
            {
                "condition_number": None,
                "condition_number_unregularized": None,
                "clipped": {n: False for n in THETA_NAMES},
                "fallback": True,
                "fallback_reason": reason,
                "uncertainty": None,
            }
        )
        return theta, details

    def effective_params(self) -> dict:
        params = {
            "k": self.k,
            "alpha": self.alpha_,
            "alpha_selection": _selection_label(self.alpha),
            "clip": self.clip,
            "fallback_k": FALLBACK_K,
        }
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


def select_ridge_alpha(
    features,
    theta,
    names,
    *,
    alphas: Sequence[float] = DEFAULT_ALPHAS,
    k: int | None = None,
):
    """Select the ridge strength by candidate-only leave-one-out.

    As :func:`select_knn_k`, for :class:`GlobalRidge` (``k=None``) or for
    :class:`LocalRidge` with neighbourhood size ``k``.

    Returns
    -------
    (alpha, table):
        The chosen alpha and a DataFrame with one row per alpha (columns as in
        :func:`select_knn_k`, ``alpha`` first).
    """
    grid = [_check_alpha(a, allow_cv=False, name="alphas entry") for a in alphas]
    if not grid:
        raise ValueError("alphas must not be empty")
    if k is None:
        make = lambda a: GlobalRidge(alpha=a)  # noqa: E731
    else:
        k = _check_k(k, allow_cv=False)
        make = lambda a: LocalRidge(k=k, alpha=a, uncertainty=False)  # noqa: E731
    runs = [_loo_errors(lambda a=a: make(a), features, theta, names) for a in grid]
    return _selection_table("alpha", grid, runs)
