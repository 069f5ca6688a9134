"""Feature standardization fitted on the candidate library only (SPEC §6).

Statistics come from the candidate library alone (population standard deviation); a
feature with std <= 1e-12 gets std 1. Queries and targets never enter the fit.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["STD_FLOOR", "Standardizer"]

#: a feature whose candidate std is at or below this is not scaled (std set to 1)
STD_FLOOR = 1e-12


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
