"""Response-library estimators of theta = (s_E, s_rho) (SPEC §6).

Semantics follow the authors' released Ficus fixture
(``tests/data/knockgs-ficus/``, README of the reference copy) exactly:

* features are standardized with statistics of the candidate library only
  (population standard deviation; a feature with std <= 1e-12 gets std 1);
* distances are Euclidean in that standardized space; equal distances are broken by
  ``case_name`` (the library is sorted by case name at ``fit``, which also makes every
  estimate bit-for-bit independent of the library's row order);
* inverse-distance weights are ``1 / (d + 1e-8)``, normalized;
* ridge fits centre the data, penalize the slopes only (unregularized intercept) and fit
  the two scales independently;
* local ridge: the k nearest candidates, equal weights, predictions clipped to the
  candidate min/max of each scale, falling back to inverse-distance KNN (k = 5) when fewer
  than 3 neighbours exist or the solve fails; the fallback is recorded.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from ..descriptors import FEATURE_NAMES
from ..errors import InputError
from ._registry import METHOD_ALIASES, METHOD_OPTIONS, canonical_method

__all__ = [
    "THETA_NAMES",
    "FEATURE_NAMES",
    "METHODS",
    "Estimate",
    "joint_error_pct",
    "Standardizer",
    "FixedDefault",
    "ResponseNearest",
    "ResponseKNN",
    "GlobalRidge",
    "LocalRidge",
    "select_knn_k",
    "select_ridge_alpha",
    "calibrate",
]

#: the two calibrated scales, in the order of every theta array
THETA_NAMES: tuple[str, str] = ("E_scale", "density_scale")

#: a feature whose candidate std is at or below this is not scaled (std set to 1)
STD_FLOOR = 1e-12
#: inverse-distance weights are 1 / (d + KNN_EPS)
KNN_EPS = 1e-8
#: local ridge needs at least this many neighbours, else it falls back to KNN
MIN_RIDGE_NEIGHBOURS = 3
#: k of the inverse-distance KNN fallback of local ridge
FALLBACK_K = 5

DEFAULT_KS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 8, 10)
DEFAULT_ALPHAS: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Estimate:
    """One frozen estimate of theta for one query case.

    Attributes
    ----------
    case_name:
        The query case.
    E_scale, density_scale:
        The estimated scales s_E and s_rho (dimensionless).
    method:
        The estimator that produced it (a key of :data:`METHODS`, or
        ``"parameter_nearest_oracle"``).
    details:
        Method-specific diagnostics (neighbours, weights, condition number, clipping,
        fallback, uncertainty); plain Python values.
    """

    case_name: str
    E_scale: float
    density_scale: float
    method: str
    details: dict = field(default_factory=dict)

    @property
    def theta(self) -> tuple[float, float]:
        """(E_scale, density_scale)."""
        return (self.E_scale, self.density_scale)

    def to_dict(self) -> dict:
        """JSON-safe record (non-finite floats become ``None``)."""
        return _json_safe(
            {
                "case_name": self.case_name,
                "E_scale": self.E_scale,
                "density_scale": self.density_scale,
                "details": self.details,
            }
        )


def _json_safe(obj: Any) -> Any:
    """Plain JSON types; NaN and infinities become None."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [_json_safe(v) for v in obj.tolist()]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return value if math.isfinite(value) else None
    return obj


def joint_error_pct(estimate, true) -> float | np.ndarray:
    """Joint parameter error ``50 * (|sE^ - sE| / sE + |sr^ - sr| / sr)`` in percent (SPEC §7).

    Parameters
    ----------
    estimate:
        An :class:`Estimate`, a pair ``(s_E, s_rho)``, or an array of pairs, shape (..., 2).
    true:
        The true scales, same shape (or an :class:`Estimate`-free pair broadcast against it).

    Returns
    -------
    float for single pairs, else an array of shape (...).
    """
    est = np.asarray(_theta_of(estimate), dtype=float)
    tru = np.asarray(_theta_of(true), dtype=float)
    if est.shape[-1:] != (2,) or tru.shape[-1:] != (2,):
        raise ValueError("joint_error_pct: expected (s_E, s_rho) pairs, shape (..., 2)")
    if not np.all(tru > 0):
        raise ValueError("joint_error_pct: true scales must be positive")
    err = 50.0 * np.sum(np.abs(est - tru) / tru, axis=-1)
    return float(err) if err.ndim == 0 else err


def _theta_of(value):
    if isinstance(value, Estimate):
        return value.theta
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], Estimate):
        return [v.theta for v in value]
    return value


# --------------------------------------------------------------------------- standardizer


class Standardizer:
    """Feature standardization fitted on the candidate library only.

    ``z = (x - mean_) / scale_`` with the population standard deviation; a feature whose
    std is at or below ``floor`` is left unscaled (``scale_ = 1``).

    Parameters
    ----------
    floor:
        Std threshold below which a feature is not scaled.
    """

    def __init__(self, *, floor: float = STD_FLOOR):
        if not (isinstance(floor, (int, float)) and math.isfinite(floor) and floor >= 0):
            raise ValueError(f"floor must be a finite number >= 0, got {floor!r}")
        self.floor = float(floor)

    def fit(self, features) -> Standardizer:
        """Fit on candidate features [n, d] (never on queries or targets)."""
        x = _as_matrix(features, "features")
        self.mean_ = x.mean(axis=0)
        std = x.std(axis=0)  # population std (ddof = 0)
        self.scale_ = np.where(std <= self.floor, 1.0, std)
        self.n_features_in_ = x.shape[1]
        return self

    def transform(self, features) -> np.ndarray:
        """Standardized copy of ``features`` [m, d]."""
        if not hasattr(self, "mean_"):
            raise RuntimeError("Standardizer is not fitted; call fit() first")
        x = _as_matrix(features, "features")
        if x.shape[1] != self.n_features_in_:
            raise ValueError(f"expected {self.n_features_in_} features, got {x.shape[1]}")
        return (x - self.mean_) / self.scale_

    def fit_transform(self, features) -> np.ndarray:
        return self.fit(features).transform(features)


def _as_matrix(values, what: str) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"{what}: expected a non-empty 2-D array [n, d], got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what}: non-finite values")
    return x


# --------------------------------------------------------------------------- estimators


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


class _LibraryEstimator:
    """Shared fit/predict plumbing: validation, candidate-only standardization, ordering."""

    method: str = ""

    def fit(self, library_features, library_theta, library_names) -> _LibraryEstimator:
        """Fit on the candidate library.

        Parameters
        ----------
        library_features:
            Candidate descriptors, shape (n, d).
        library_theta:
            Candidate scales (s_E, s_rho), shape (n, 2), positive.
        library_names:
            Candidate case names, n unique strings (they break distance ties).

        Returns
        -------
        self
        """
        x = _as_matrix(library_features, "library_features")
        theta = np.asarray(library_theta, dtype=float)
        if theta.shape != (x.shape[0], 2):
            raise ValueError(
                f"library_theta: expected shape ({x.shape[0]}, 2), got {theta.shape}"
            )
        if not np.all(np.isfinite(theta)) or not np.all(theta > 0):
            raise ValueError("library_theta: scales must be finite and positive")
        names = [str(n) for n in library_names]
        if len(names) != x.shape[0]:
            raise ValueError(f"library_names: expected {x.shape[0]} names, got {len(names)}")
        if len(set(names)) != len(names):
            raise ValueError("library_names: duplicate case names")
        order = sorted(range(len(names)), key=names.__getitem__)
        self.features_ = x[order]
        self.theta_ = theta[order]
        self.names_ = [names[i] for i in order]
        self.standardizer_ = Standardizer().fit(self.features_)
        self.z_ = self.standardizer_.transform(self.features_)
        self.theta_min_ = self.theta_.min(axis=0)
        self.theta_max_ = self.theta_.max(axis=0)
        self.n_features_in_ = x.shape[1]
        self._fit_method()
        return self

    def _fit_method(self) -> None:
        pass

    def predict(self, query_features, *, names: Sequence[str] | None = None) -> list[Estimate]:
        """Estimate theta for each query descriptor.

        Parameters
        ----------
        query_features:
            Query descriptors, shape (m, d) (or (d,) for one query).
        names:
            Query case names (default ``query_0``, ``query_1``, ...).
        """
        if not hasattr(self, "z_"):
            raise RuntimeError(f"{type(self).__name__} is not fitted; call fit() first")
        zq = self.standardizer_.transform(_as_matrix(query_features, "query_features"))
        if names is None:
            names = [f"query_{i}" for i in range(zq.shape[0])]
        names = [str(n) for n in names]
        if len(names) != zq.shape[0]:
            raise ValueError(f"names: expected {zq.shape[0]} names, got {len(names)}")
        out = []
        for name, z in zip(names, zq):
            (e, r), details = self._predict_one(z)
            out.append(Estimate(name, float(e), float(r), self.method, details))
        return out

    def effective_params(self) -> dict:
        """The settings in force after ``fit`` (CV-selected values resolved)."""
        return {}

    # helpers -----------------------------------------------------------------------
    def _neighbours(self, z: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Indices and distances of the k nearest candidates, ties broken by case name."""
        d = np.sqrt(np.sum((self.z_ - z) ** 2, axis=1))
        # names_ is sorted, so a stable sort on distance breaks ties by case name
        idx = np.argsort(d, kind="stable")[: min(k, d.size)]
        return idx, d[idx]

    def _knn(self, z: np.ndarray, k: int, weighting: str) -> tuple[np.ndarray, dict]:
        idx, d = self._neighbours(z, k)
        if weighting == "distance":
            w = 1.0 / (d + KNN_EPS)
        else:
            w = np.ones_like(d)
        w = w / w.sum()
        theta = w @ self.theta_[idx]
        details = {
            "k": int(k),
            "k_used": int(idx.size),
            "weighting": weighting,
            "neighbours": [self.names_[i] for i in idx],
            "distances": d.tolist(),
            "weights": w.tolist(),
        }
        return theta, details


class FixedDefault(_LibraryEstimator):
    """Fixed default material: ignores the response evidence by construction.

    Parameters
    ----------
    theta:
        The default scales (s_E, s_rho); SPEC §4 default (1, 1).
    """

    method = "fixed_default"

    def __init__(self, *, theta: tuple[float, float] = (1.0, 1.0)):
        t = np.asarray(theta, dtype=float)
        if t.shape != (2,) or not np.all(np.isfinite(t)) or not np.all(t > 0):
            raise ValueError(f"theta must be two finite positive scales, got {theta!r}")
        self.theta = (float(t[0]), float(t[1]))

    def _predict_one(self, z):
        return self.theta, {"theta_default": list(self.theta)}

    def effective_params(self) -> dict:
        return {"theta": list(self.theta)}


class ResponseNearest(_LibraryEstimator):
    """The single candidate nearest in standardized descriptor space."""

    method = "response_nearest"

    def _predict_one(self, z):
        idx, d = self._neighbours(z, 1)
        i = int(idx[0])
        return self.theta_[i], {"neighbour": self.names_[i], "distance": float(d[0])}


class ResponseKNN(_LibraryEstimator):
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
        params = {"k": self.k_, "weights": self.weights, "k_selection": _selection(self.k)}
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


def _selection(value) -> str:
    return "cv" if value == "cv" else "fixed"


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


class GlobalRidge(_LibraryEstimator):
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
            "alpha_selection": _selection(self.alpha),
            "n_candidates": len(self.names_),
            "condition_number": self.fit_.condition_number,
            "coefficients": _coef_details(self.fit_),
        }

    def effective_params(self) -> dict:
        params = {"alpha": self.alpha_, "alpha_selection": _selection(self.alpha)}
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


class LocalRidge(_LibraryEstimator):
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
            "alpha_selection": _selection(self.alpha),
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
            "alpha_selection": _selection(self.alpha),
            "clip": self.clip,
            "fallback_k": FALLBACK_K,
        }
        if self.cv_table_ is not None:
            params["cv_table"] = self.cv_table_.to_dict(orient="records")
        return params


#: deployable estimators, by method name (the parameter-nearest oracle is not one)
METHODS: dict[str, type[_LibraryEstimator]] = {
    "fixed_default": FixedDefault,
    "response_nearest": ResponseNearest,
    "response_knn": ResponseKNN,
    "global_ridge": GlobalRidge,
    "local_ridge": LocalRidge,
}


# --------------------------------------------------------------------------- selection


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


# --------------------------------------------------------------------------- tables


def _as_table(table, default_source: str):
    import pandas as pd

    if isinstance(table, pd.DataFrame):
        return table, default_source
    if isinstance(table, (str, os.PathLike)):
        source = os.fspath(table)
        try:
            return pd.read_csv(source, dtype={"case_name": str}, keep_default_na=False,
                               na_values=[""]), source
        except FileNotFoundError:
            raise InputError(source, "file", "no such file") from None
        except Exception as exc:
            raise InputError(source, "file", f"cannot read CSV: {exc}") from None
    raise InputError(
        default_source, "table", f"expected a DataFrame or a CSV path, got {type(table).__name__}"
    )


def _case_names(df, source) -> list[str]:
    if "case_name" not in df.columns:
        raise InputError(source, "case_name", "missing column")
    col = df["case_name"]
    if col.isna().any() or (col.astype(str).str.strip() == "").any():
        raise InputError(source, "case_name", "empty case name")
    names = col.astype(str).tolist()
    seen, dup = set(), []
    for n in names:
        if n in seen and n not in dup:
            dup.append(n)
        seen.add(n)
    if dup:
        raise InputError(source, "case_name", f"duplicate case names {dup[:5]}")
    return names


def _numeric(df, source, columns, names) -> np.ndarray:
    import pandas as pd

    out = np.empty((len(df), len(columns)))
    for j, col in enumerate(columns):
        if col not in df.columns:
            raise InputError(source, col, "missing column")
        values = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            cases = [names[i] for i in np.flatnonzero(bad)[:5]]
            raise InputError(source, col, f"non-finite or non-numeric value (cases {cases})")
        out[:, j] = values
    return out


def _library_hash(names, theta, features) -> str:
    order = sorted(range(len(names)), key=names.__getitem__)
    rows = [[names[i], *map(repr, theta[i].tolist()), *map(repr, features[i].tolist())]
            for i in order]
    payload = json.dumps({"columns": ["case_name", *THETA_NAMES, *FEATURE_NAMES], "rows": rows})
    return hashlib.sha256(payload.encode()).hexdigest()


_METHOD_PARAMS = METHOD_OPTIONS


def _deployable_method(method) -> str:
    """The canonical name of a deployable ``method`` (aliases accepted), or an InputError."""
    try:
        name = canonical_method(method)
    except ValueError:
        name = None
    if name not in METHODS:
        hint = " (the parameter-nearest oracle reads target labels and is evaluation-only)" \
            if "oracle" in str(method) else ""
        aliases = ", ".join(f"{a} ({c})" for a, c in METHOD_ALIASES.items())
        raise InputError("calibrate", "method",
                         f"unknown method {method!r}; allowed: {', '.join(METHODS)}; aliases: {aliases}{hint}")
    return name


def calibrate(library, queries, method: str, **params) -> dict:
    """Estimate theta for every query from a candidate library (the ``knockgs calibrate`` core).

    Parameters
    ----------
    library:
        DataFrame or CSV path with ``case_name``, ``E_scale``, ``density_scale`` and the five
        :data:`FEATURE_NAMES` columns; other columns are ignored.
    queries:
        DataFrame or CSV path with ``case_name`` and the five feature columns; other columns
        (labels, Probe-B descriptors) are ignored and cannot influence the estimates.
    method:
        One of :data:`METHODS` (the parameter-nearest oracle is not deployable, so not here).
    **params:
        Estimator options (``k``, ``alpha``, ``weights``, ...); an option the method does not
        take is an error.

    Returns
    -------
    dict
        ``{"method", "params", "library": {"n_candidates", "sha256"}, "features",
        "predictions": [{"case_name", "E_scale", "density_scale", "details"}]}``, JSON-safe
        (no NaN), predictions in query order. ``library.sha256`` hashes the used library
        columns, sorted by case name.

    Raises
    ------
    InputError
        Missing columns, non-finite values, non-positive scales, duplicate case names, case
        names shared by library and queries, unknown method or option, bad option values.
    """
    lib_df, lib_src = _as_table(library, "library table")
    q_df, q_src = _as_table(queries, "query table")
    method = _deployable_method(method)
    unknown = sorted(set(params) - set(_METHOD_PARAMS[method]))
    if unknown:
        allowed = ", ".join(_METHOD_PARAMS[method]) or "none"
        raise InputError("calibrate", unknown[0],
                         f"not an option of method {method!r} (options: {allowed})")

    lib_names = _case_names(lib_df, lib_src)
    theta = _numeric(lib_df, lib_src, THETA_NAMES, lib_names)
    for j, col in enumerate(THETA_NAMES):
        bad = theta[:, j] <= 0
        if bad.any():
            cases = [lib_names[i] for i in np.flatnonzero(bad)[:5]]
            raise InputError(lib_src, col, f"scales must be positive (cases {cases})")
    features = _numeric(lib_df, lib_src, FEATURE_NAMES, lib_names)
    if len(lib_names) == 0:
        raise InputError(lib_src, "case_name", "empty library")
    q_names = _case_names(q_df, q_src)
    q_features = _numeric(q_df, q_src, FEATURE_NAMES, q_names)
    if len(q_names) == 0:
        raise InputError(q_src, "case_name", "no queries")
    shared = sorted(set(q_names) & set(lib_names))
    if shared:
        raise InputError(q_src, "case_name", f"case names also in the library: {shared[:5]}")

    try:
        estimator = METHODS[method](**params)
    except ValueError as exc:
        field_name = next((p for p in params if str(exc).startswith(p + " ")), "params")
        raise InputError("calibrate", field_name, str(exc)) from None
    try:
        estimator.fit(features, theta, lib_names)
    except ValueError as exc:
        raise InputError(lib_src, "library", str(exc)) from None
    estimates = estimator.predict(q_features, names=q_names)
    return _json_safe(
        {
            "method": method,
            "params": estimator.effective_params(),
            "library": {
                "n_candidates": len(lib_names),
                "sha256": _library_hash(lib_names, theta, features),
            },
            "features": list(FEATURE_NAMES),
            "predictions": [e.to_dict() for e in estimates],
        }
    )
