"""The ``knockgs calibrate`` core: frozen estimates for query descriptors from a library."""

from __future__ import annotations

import warnings

from ..io import json_safe
from ..descriptors import FEATURE_NAMES
from ..errors import InputError, InputWarning
from ._registry import METHOD_ALIASES, METHOD_OPTIONS, METHODS, canonical_method
from ._tables import library_arrays, library_design, library_hash, query_arrays, read_table

__all__ = ["calibrate"]


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
        A canonical name of :data:`DEPLOYABLE_METHODS` or one of its aliases
        (:data:`METHOD_ALIASES`); the parameter-nearest oracle is not deployable, so not here.
    **params:
        Estimator options (``k``, ``alpha``, ``weights``, ...); an option the method does not
        take is an error.

    Returns
    -------
    dict
        ``{"method", "params", "library": {"n_candidates", "sha256"}, "features",
        "predictions": [{"case_name", "E_scale", "density_scale", "details"}]}``, JSON-safe
        (:func:`knockgs_core.io.json_safe`: no NaN), predictions in query order. ``method``
        is the canonical name; ``library.sha256`` hashes the used library columns, sorted by
        case name.

    Raises
    ------
    InputError
        Missing columns, non-finite values, non-positive scales, duplicate case names, case
        names shared by library and queries, unknown method or option, bad option values,
        ``k`` above the library's candidate count, a library whose candidates all have the same
        descriptors. A library whose descriptors vary along one direction only is flagged
        (``library.degenerate`` and an :class:`~knockgs_core.errors.InputWarning`), and so are
        estimates that fell back to inverse-distance KNN (a warning; their details say why).
    """
    lib_df, lib_src = read_table(library, "library table")
    q_df, q_src = read_table(queries, "query table")
    method = _deployable_method(method)
    unknown = sorted(set(params) - set(METHOD_OPTIONS[method]))
    if unknown:
        allowed = ", ".join(METHOD_OPTIONS[method]) or "none"
        raise InputError("calibrate", unknown[0],
                         f"not an option of method {method!r} (options: {allowed})")

    lib_names, theta, features = library_arrays(lib_df, lib_src)
    q_names, q_features = query_arrays(q_df, q_src, lib_names)
    k = params.get("k")
    if isinstance(k, int) and not isinstance(k, bool) and k > len(lib_names):
        raise InputError(lib_src, "k", f"k = {k} neighbours, but the library has only {len(lib_names)} candidates")
    degenerate = library_design(features, lib_src)
    if degenerate is not None:
        warnings.warn(f"{lib_src}: {degenerate}", InputWarning, stacklevel=2)

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
    fallbacks = [e for e in estimates if (e.details or {}).get("fallback")]
    if fallbacks:
        reasons = sorted({str(e.details.get("fallback_reason")) for e in fallbacks})
        warnings.warn(f"{lib_src}: {len(fallbacks)} of {len(estimates)} estimates fell back from {method} to "
                      f"inverse-distance KNN ({'; '.join(reasons)})", InputWarning, stacklevel=2)
    return json_safe(
        {
            "method": method,
            "params": estimator.effective_params(),
            "library": {
                "n_candidates": len(lib_names),
                "sha256": library_hash(lib_names, theta, features),
                **({"degenerate": degenerate} if degenerate is not None else {}),
            },
            "features": list(FEATURE_NAMES),
            "predictions": [e.to_dict() for e in estimates],
        }
    )
