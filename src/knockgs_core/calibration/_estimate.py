"""One frozen estimate of theta = (s_E, s_rho) and the joint parameter error (SPEC §7)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io import json_safe

__all__ = ["THETA_NAMES", "Estimate", "joint_error_pct"]

#: the two calibrated scales, in the order of every theta array
THETA_NAMES: tuple[str, str] = ("E_scale", "density_scale")


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
        The estimator that produced it (a canonical name of :data:`METHOD_NAMES`).
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
        """JSON-safe record (:func:`knockgs_core.io.json_safe`: NaN becomes ``None``,
        +-infinity ``"inf"`` / ``"-inf"``)."""
        return json_safe(
            {
                "case_name": self.case_name,
                "E_scale": self.E_scale,
                "density_scale": self.density_scale,
                "details": self.details,
            }
        )


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
