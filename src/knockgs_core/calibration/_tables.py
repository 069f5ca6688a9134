"""The library and query tables of :func:`calibrate`: reading, validation, library hash.

Errors are :class:`~knockgs_core.errors.InputError` naming the file (or the table's role)
and the offending column.
"""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from ..descriptors import FEATURE_NAMES
from ..errors import InputError
from ._estimate import THETA_NAMES

__all__ = ["read_table", "library_arrays", "query_arrays", "library_hash"]


def read_table(table, default_source: str):
    """``(DataFrame, source)``: ``table`` itself when a DataFrame (named ``default_source`` in
    errors), else the CSV at that path (named by its path); case names are read as strings."""
    import pandas as pd

    if isinstance(table, pd.DataFrame):
        return table, default_source
    if isinstance(table, (str, os.PathLike)):
        source = os.fspath(table)
        try:
            return pd.read_csv(source, dtype={"case_name": str}, keep_default_na=False,
                               na_values=[""]), source
        except FileNotFoundError:
            raise InputError(source, "file", "no such file") from None
        except Exception as exc:
            raise InputError(source, "file", f"cannot read CSV: {exc}") from None
    raise InputError(
        default_source, "table", f"expected a DataFrame or a CSV path, got {type(table).__name__}"
    )


def _case_names(df, source) -> list[str]:
    if "case_name" not in df.columns:
        raise InputError(source, "case_name", "missing column")
    col = df["case_name"]
    if col.isna().any() or (col.astype(str).str.strip() == "").any():
        raise InputError(source, "case_name", "empty case name")
    names = col.astype(str).tolist()
    seen, dup = set(), []
    for n in names:
        if n in seen and n not in dup:
            dup.append(n)
        seen.add(n)
    if dup:
        raise InputError(source, "case_name", f"duplicate case names {dup[:5]}")
    return names


def _numeric(df, source, columns, names) -> np.ndarray:
    import pandas as pd

    out = np.empty((len(df), len(columns)))
    for j, col in enumerate(columns):
        if col not in df.columns:
            raise InputError(source, col, "missing column")
        values = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            cases = [names[i] for i in np.flatnonzero(bad)[:5]]
            raise InputError(source, col, f"non-finite or non-numeric value (cases {cases})")
        out[:, j] = values
    return out


def library_hash(names, theta, features) -> str:
    """SHA-256 of the used library columns (``case_name``, scales, features), rows sorted by
    case name, floats by ``repr``: the same library gives the same hash in any row order."""
    order = sorted(range(len(names)), key=names.__getitem__)
    rows = [[names[i], *map(repr, theta[i].tolist()), *map(repr, features[i].tolist())]
            for i in order]
    payload = json.dumps({"columns": ["case_name", *THETA_NAMES, *FEATURE_NAMES], "rows": rows})
    return hashlib.sha256(payload.encode()).hexdigest()


def library_arrays(df, source) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Validated candidate library: case names, scales (s_E, s_rho) [n, 2] (positive) and
    features [n, 5] (finite), in table order."""
    lib_names = _case_names(df, source)
    theta = _numeric(df, source, THETA_NAMES, lib_names)
    for j, col in enumerate(THETA_NAMES):
        bad = theta[:, j] <= 0
        if bad.any():
            cases = [lib_names[i] for i in np.flatnonzero(bad)[:5]]
            raise InputError(source, col, f"scales must be positive (cases {cases})")
    features = _numeric(df, source, FEATURE_NAMES, lib_names)
    if len(lib_names) == 0:
        raise InputError(source, "case_name", "empty library")
    return lib_names, theta, features


def query_arrays(df, source, lib_names) -> tuple[list[str], np.ndarray]:
    """Validated queries: case names (none shared with the library) and features [m, 5]."""
    q_names = _case_names(df, source)
    q_features = _numeric(df, source, FEATURE_NAMES, q_names)
    if len(q_names) == 0:
        raise InputError(source, "case_name", "no queries")
    shared = sorted(set(q_names) & set(lib_names))
    if shared:
        raise InputError(source, "case_name", f"case names also in the library: {shared[:5]}")
    return q_names, q_features
