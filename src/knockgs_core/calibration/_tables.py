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
from ..io import input_problem
from ._estimate import THETA_NAMES

__all__ = ["read_table", "library_arrays", "library_design", "query_arrays", "library_hash"]


def read_table(table, default_source: str):
    """``(DataFrame, source)``: ``table`` itself when a DataFrame (named ``default_source`` in
    errors), else the CSV at that path (named by its path); case names are read as strings."""
    import pandas as pd

    if isinstance(table, pd.DataFrame):
        return table, default_source
    if isinstance(table, (str, os.PathLike)):
        source = os.fspath(table)
        problem = input_problem(source)  # a FIFO would block pandas, a device never end the read
        if problem is not None:
            raise InputError(source, "file", problem)
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


#: a direction of the centred library descriptors counts when its singular value is above this
#: share of the largest one
DESIGN_RTOL = 1e-6


def library_design(features, source) -> str | None:
    """Judge a library's design: the rank of its centred descriptors [n, 5].

    Every candidate with the same descriptors (rank 0) tells no theta from another: refused
    (:class:`InputError` naming ``source``). Descriptors that vary along one direction only
    (rank 1: e.g. two candidates, or every descriptor a multiple of one) cannot separate the two
    scales: returned as a sentence for the estimate and stderr to flag. None for a sound design.
    """
    x = np.asarray(features, dtype=float)
    centred = x - x.mean(axis=0)
    scale = np.abs(x).max() if x.size else 0.0
    sv = np.linalg.svd(centred, compute_uv=False) if x.shape[0] > 1 else np.zeros(1)
    # rank at the precision a descriptor table is written with (10 digits) and a little more:
    # a direction a millionth of the main one is the tables' rounding, not information
    rank = 0 if sv[0] <= 1e-12 * max(scale, 1e-300) * len(x) else int(np.sum(sv > DESIGN_RTOL * sv[0]))
    if rank == 0:
        raise InputError(source, "features", f"degenerate library: all {x.shape[0]} candidates have the same "
                         "descriptors, so no estimate can tell one theta from another")
    if rank < 2:
        return (f"degenerate library design: the {x.shape[0]} candidates' descriptors vary along {rank} direction "
                "only, fewer than the two scales (s_E, s_rho) to be told apart; the estimates are not identified")
    return None


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
