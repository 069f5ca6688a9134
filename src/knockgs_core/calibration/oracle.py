"""Parameter-nearest oracle: an evaluation-only diagnostic, never a deployable estimator.

It reads the hidden target scales, so it lives apart from the deployable namespace
(``knockgs_core.calibration`` does not import or re-export it) and is not a method of
``knockgs calibrate``. It answers "how good is the best single library candidate for this
target?", the floor of any estimator that returns a library member.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from ._estimate import THETA_NAMES, Estimate, joint_error_pct
from ._registry import ORACLE_METHOD

__all__ = ["ParameterNearestOracle"]


class ParameterNearestOracle:
    """The candidate nearest to the hidden target in parameter space (evaluation only).

    Parameters
    ----------
    metric:
        ``"joint_error"`` (default): the candidate minimizing the joint error
        ``50 * (|sE_c - sE| / sE + |sr_c - sr| / sr)`` to the target, i.e. the nearest in
        relative parameter space; ``"standardized"``: Euclidean distance in parameter space
        standardized by the candidates' population std. Ties go to the first case name.
    """

    method = ORACLE_METHOD

    def __init__(self, *, metric: Literal["joint_error", "standardized"] = "joint_error"):
        if metric not in ("joint_error", "standardized"):
            raise ValueError(f"metric must be one of 'joint_error', 'standardized'; got {metric!r}")
        self.metric = metric

    def fit(self, library_features, library_theta, library_names) -> ParameterNearestOracle:
        """Store the candidates (``library_features`` is accepted for API symmetry, unused)."""
        theta = np.asarray(library_theta, dtype=float)
        if theta.ndim != 2 or theta.shape[1] != 2 or theta.shape[0] == 0:
            raise ValueError(f"library_theta: expected shape (n, 2), got {theta.shape}")
        if not np.all(np.isfinite(theta)) or not np.all(theta > 0):
            raise ValueError("library_theta: scales must be finite and positive")
        names = [str(n) for n in library_names]
        if len(names) != theta.shape[0] or len(set(names)) != len(names):
            raise ValueError("library_names: expected one unique name per candidate")
        order = sorted(range(len(names)), key=names.__getitem__)
        self.theta_ = theta[order]
        self.names_ = [names[i] for i in order]
        std = self.theta_.std(axis=0)
        self.scale_ = np.where(std <= 1e-12, 1.0, std)
        return self

    def predict(self, target_theta, *, names: Sequence[str] | None = None) -> list[Estimate]:
        """The nearest candidate to each hidden target (s_E, s_rho), shape (m, 2)."""
        if not hasattr(self, "theta_"):
            raise RuntimeError("ParameterNearestOracle is not fitted; call fit() first")
        targets = np.atleast_2d(np.asarray(target_theta, dtype=float))
        if targets.shape[1] != 2 or not np.all(np.isfinite(targets)) or not np.all(targets > 0):
            raise ValueError("target_theta: expected finite positive pairs, shape (m, 2)")
        if names is None:
            names = [f"query_{i}" for i in range(targets.shape[0])]
        out = []
        for name, target in zip(names, targets):
            if self.metric == "joint_error":
                score = joint_error_pct(self.theta_, target)
            else:
                score = np.sqrt(np.sum(((self.theta_ - target) / self.scale_) ** 2, axis=1))
            i = int(np.argmin(score))  # names_ sorted: first minimum = first case name
            e, r = self.theta_[i]
            out.append(
                Estimate(
                    str(name),
                    float(e),
                    float(r),
                    self.method,
                    {
                        "neighbour": self.names_[i],
                        "metric": self.metric,
                        "score": float(score[i]),
                        "deployable": False,
                        "reads_target": dict(zip(THETA_NAMES, map(float, target))),
                    },
                )
            )
        return out
