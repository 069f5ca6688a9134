"""The calibration method vocabulary: one list of names that every layer derives from.

The canonical names are the names of the paper's tables. The CLI ``choices``, the
workflow's wildcard constraint, the config schema's enum and the accepted method options
all come from here, and :data:`METHODS` maps each deployable name to its estimator class.
The older short spellings (``default``, ``nearest``, ``knn``) are accepted as aliases and
mapped to their canonical names by :func:`canonical_method`.
"""

from __future__ import annotations

from ._base import LibraryEstimator
from ._fixed_default import FixedDefault
from ._neighbors import ResponseKNN, ResponseNearest
from ._ridge import GlobalRidge, LocalRidge

__all__ = [
    "METHODS",
    "METHOD_NAMES",
    "DEPLOYABLE_METHODS",
    "ORACLE_METHOD",
    "METHOD_ALIASES",
    "METHOD_OPTIONS",
    "canonical_method",
]

#: the evaluation-only parameter-nearest oracle: it reads hidden target labels
ORACLE_METHOD: str = "parameter_nearest_oracle"

#: the deployable methods (they see only the candidate library and the query descriptors),
#: in table order
DEPLOYABLE_METHODS: tuple[str, ...] = (
    "fixed_default",
    "response_nearest",
    "response_knn",
    "global_ridge",
    "local_ridge",
)

#: every method of the tables, in table order: the deployable ones, then the oracle
METHOD_NAMES: tuple[str, ...] = (*DEPLOYABLE_METHODS, ORACLE_METHOD)

#: deployable estimators, by canonical name (the parameter-nearest oracle is not one: it
#: lives in :mod:`knockgs_core.calibration.oracle`)
METHODS: dict[str, type[LibraryEstimator]] = {
    "fixed_default": FixedDefault,
    "response_nearest": ResponseNearest,
    "response_knn": ResponseKNN,
    "global_ridge": GlobalRidge,
    "local_ridge": LocalRidge,
}

#: older spellings -> canonical name
METHOD_ALIASES: dict[str, str] = {
    "default": "fixed_default",
    "nearest": "response_nearest",
    "knn": "response_knn",
}

#: canonical name -> the options (keyword arguments) its estimator accepts
METHOD_OPTIONS: dict[str, tuple[str, ...]] = {
    "fixed_default": ("theta",),
    "response_nearest": (),
    "response_knn": ("k", "weights", "ks"),
    "global_ridge": ("alpha", "alphas"),
    "local_ridge": ("k", "alpha", "alphas", "clip", "uncertainty"),
    ORACLE_METHOD: ("metric",),
}


def canonical_method(name: str) -> str:
    """The canonical name of method ``name`` (a canonical name or an alias).

    Raises
    ------
    ValueError
        ``name`` is neither a canonical name nor an alias; the message lists both.
    """
    if isinstance(name, str):
        if name in METHOD_NAMES:
            return name
        if name in METHOD_ALIASES:
            return METHOD_ALIASES[name]
    aliases = ", ".join(f"{a} ({c})" for a, c in METHOD_ALIASES.items())
    raise ValueError(f"unknown method {name!r}; allowed: {', '.join(METHOD_NAMES)}; aliases: {aliases}")
