"""Response-nearest-neighbour estimators: the nearest candidate, and the k nearest averaged; the
selection of k by candidate-only leave-one-out (:func:`select_knn_k`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from ._base import LibraryEstimator
from ._selection import DEFAULT_KS, _check_k, _loo_errors, _selection_label, _selection_table
from ._standardize import _as_matrix

__all__ = ["ResponseNearest", "ResponseKNN", "select_knn_k"]


class ResponseNearest(LibraryEstimator):
    """The single candidate nearest in standardized descriptor space."""

    method = "response_nearest"

    def _predict_one(self, z):
        idx, d = self._neighbours(z, 1)
        i = int(idx[0])
        return self.theta_[i], {"neighbour": self.names_[i], "distance": float(d[0])}


class ResponseKNN(LibraryEstimator):
    """K nearest candidates in standardized descriptor space, weighted average of theta.

    Parameters
    ----------
    k:
        Neighbour count, or ``"cv"`` to select it by candidate-only leave-one-out
        (:func:`select_knn_k`) at ``fit``; the authors' Ficus setting is 3. A library
        smaller than k uses all candidates (``k_used`` in the details).
    weights:
        ``"distance"`` (1 / (d + 1e-8), normalized) or ``"uniform"``.
    ks:
        Grid searched when ``k="cv"``.
    """

    method = "response_knn"

    def __init__(
        self,
        *,
        k: int | Literal["cv"] = 3,
        weights: Literal["distance", "uniform"] = "distance",
        ks: Sequence[int] = DEFAULT_KS,
    ):
        self.k = _check_k(k, allow_cv=True)
        if weights not in ("distance", "uniform"):
            raise ValueError(f"weights must be one of 'distance', 'uniform'; got {weights!r}")
        self.weights = weights
        self.ks = tuple(_check_k(v, allow_cv=False, name="ks entry") for v in ks)
        if not self.ks:
            raise ValueError("ks must not be empty")

    def _fit_method(self):
        if self.k == "cv":
            self.k_, self.cv_table_ = select_knn_k(
                self.features_, self.theta_, self.names_, ks=self.ks, weights=self.weights
            )
        else:
            self.k_, self.cv_table_ = self.k, None

    def _predict_one(self, z):
        theta, details = self._knn(z, self.k_, self.weights)
        details["k_selection"] = "cv" if self.k == "cv" else "fixed"
        return theta, details

    def effective_params(self) -> dict:
        params = {"k": self.k_, "weights": self.weights, "k_selection": _selection_label(self.k)}
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


def select_knn_k(
    features,
    theta,
    names,
    *,
    ks: Sequence[int] = DEFAULT_KS,
    weights: Literal["distance", "uniform"] = "distance",
):
    """Select the KNN neighbour count by candidate-only leave-one-out.

    Each candidate in turn is held out; the standardizer and the estimator are refitted on
    the others and the held-out candidate's scales are predicted from its descriptor. The
    k with the lowest mean joint error wins (the first in ``ks`` among equal means). Values
    of k larger than a fold's training set (n - 1) are skipped.

    Returns
    -------
    (k, table):
        The chosen k and a DataFrame with one row per evaluated k: ``k``,
        ``mean_joint_error_pct``, ``max_joint_error_pct``, ``n_folds``, ``n_fallbacks``,
        ``selected``.
    """
    x = _as_matrix(features, "features")
    grid = [_check_k(k, allow_cv=False, name="ks entry") for k in ks]
    grid = [k for k in grid if k <= x.shape[0] - 1]
    if not grid:
        raise ValueError(f"no k in {tuple(ks)} fits a leave-one-out fold of {x.shape[0] - 1}")
    runs = [_loo_errors(lambda k=k: ResponseKNN(k=k, weights=weights), x, theta, names)
            for k in grid]
    return _selection_table("k", grid, runs)
