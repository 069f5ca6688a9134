"""Deployable estimators of theta = (s_E, s_rho) from a Probe-A response library (SPEC §6).

Every estimator here sees only the candidate library and the query descriptors. The
evaluation-only parameter-nearest oracle, which reads hidden target labels, is kept out of
this namespace: import it explicitly from :mod:`knockgs_core.calibration.oracle`. Its name,
:data:`ORACLE_METHOD`, is part of the method vocabulary (:data:`METHOD_NAMES`), which every
layer (CLI, workflow, config schema) derives from.
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
from ._registry import (
    DEPLOYABLE_METHODS,
    METHOD_ALIASES,
    METHOD_NAMES,
    METHOD_OPTIONS,
    ORACLE_METHOD,
    canonical_method,
)

__all__ = [
    "METHOD_NAMES",
    "DEPLOYABLE_METHODS",
    "ORACLE_METHOD",
    "METHOD_ALIASES",
    "METHOD_OPTIONS",
    "canonical_method",
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
