"""The fixed-default baseline: one material for every query, whatever the response."""

from __future__ import annotations

import numpy as np

from ._base import LibraryEstimator

__all__ = ["FixedDefault"]


class FixedDefault(LibraryEstimator):
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
