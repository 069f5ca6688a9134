"""Deployable estimators of theta = (s_E, s_rho) from a Probe-A response library (SPEC §6).

Every estimator here sees only the candidate library and the query descriptors. The
evaluation-only parameter-nearest oracle, which reads hidden target labels, is kept out of
this namespace: import it explicitly from :mod:`knockgs_core.calibration.oracle`. Its name,
:data:`ORACLE_METHOD`, is part of the method vocabulary (:data:`METHOD_NAMES`), which every
layer (CLI, workflow, config schema) derives from.

Semantics follow the authors' released Ficus fixture (``tests/data/knockgs-ficus/``) exactly:
features standardized on the candidates only; Euclidean distances in that space, ties broken
by case name; inverse-distance weights ``1 / (d + 1e-8)``; ridge fits with an unregularized
intercept, the two scales fitted independently; local ridge clipped to the candidate bounds,
falling back to inverse-distance KNN (k = 5) when it cannot fit.

Modules: ``_registry`` (method names, aliases, options, :data:`METHODS`), ``_estimate``
(:class:`Estimate`, :func:`joint_error_pct`), ``_standardize``, ``_base`` (shared fit /
predict / neighbour search), ``_fixed_default``, ``_selection`` (k / alpha checks, grids and
the candidate-only leave-one-out), ``_neighbors`` (response nearest, KNN, the selection of k),
``_ridge`` (global and local ridge, the selection of alpha), ``_tables`` (library and query
tables, library hash), ``_calibrate`` (the ``knockgs calibrate`` core).
"""

from ..descriptors import FEATURE_NAMES
from ._calibrate import calibrate
from ._estimate import THETA_NAMES, Estimate, joint_error_pct
from ._fixed_default import FixedDefault
from ._neighbors import ResponseKNN, ResponseNearest, select_knn_k
from ._registry import (
    DEPLOYABLE_METHODS,
    METHOD_ALIASES,
    METHOD_NAMES,
    METHOD_OPTIONS,
    METHODS,
    ORACLE_METHOD,
    canonical_method,
)
from ._ridge import GlobalRidge, LocalRidge, select_ridge_alpha
from ._selection import DEFAULT_ALPHAS, DEFAULT_KS
from ._standardize import Standardizer

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
