"""The shared plumbing of the library estimators: fit, predict, neighbour search (SPEC §6).

Semantics follow the authors' released Ficus fixture (``tests/data/knockgs-ficus/``):
features are standardized on the candidates only (:class:`Standardizer`); distances are
Euclidean in that space; equal distances are broken by ``case_name`` (the library is
sorted by case name at ``fit``, which also makes every estimate bit-for-bit independent of
the library's row order); inverse-distance weights are ``1 / (d + 1e-8)``, normalized.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ._estimate import Estimate
from ._standardize import Standardizer, _as_matrix

__all__ = ["KNN_EPS", "LibraryEstimator"]

#: inverse-distance weights are 1 / (d + KNN_EPS)
KNN_EPS = 1e-8


class LibraryEstimator:
    """Shared fit/predict plumbing: validation, candidate-only standardization, ordering."""

    method: str = ""

    def fit(self, library_features, library_theta, library_names) -> LibraryEstimator:
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
