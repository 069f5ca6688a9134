"""Response-nearest-neighbour estimators: the nearest candidate, and the k nearest averaged."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from ._base import LibraryEstimator
from ._selection import DEFAULT_KS, _check_k, _selection_label, select_knn_k

__all__ = ["ResponseNearest", "ResponseKNN"]


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
