"""Deployable estimators of theta = (s_E, s_rho) from a Probe-A response library (SPEC §6).

Every estimator here sees only the candidate library and the query descriptors. The
evaluation-only parameter-nearest oracle, which reads hidden target labels, is kept out of
this namespace: import it explicitly from :mod:`knockgs_core.calibration.oracle`.
"""

from ._impl import (
    DEFAULT_ALPHAS,
    DEFAULT_KS,
    FEATURE_NAMES,
    METHODS,
    THETA_NAMES,
    Estimate,
    FixedDefault,
    GlobalRidge,
    LocalRidge,
    ResponseKNN,
    ResponseNearest,
    Standardizer,
    calibrate,
    joint_error_pct,
    select_knn_k,
    select_ridge_alpha,
)

__all__ = [
    "THETA_NAMES",
    "FEATURE_NAMES",
    "METHODS",
    "DEFAULT_KS",
    "DEFAULT_ALPHAS",
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
