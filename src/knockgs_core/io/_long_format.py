"""The long Parquet format of per-particle trajectories: the one reader.

A long-format file has one row per (frame, particle): integer columns ``frame`` and
``particle`` and float value columns (``x``, ``y``, ``z`` for positions; ``F00`` .. ``F22``
for deformation gradients). Rollouts, deformation-gradient files and every table derived
from them are read here; the writer lives with the rollout (:mod:`knockgs_core.rollout`).
This module imports neither Warp nor the simulator, so descriptors and audits can use it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Sequence
from typing import Union

import numpy as np

from ..errors import InputError
from ._inputs import input_problem

__all__ = ["POSITION_COLUMNS", "read_long_values", "read_positions", "read_metadata", "check_rollout_meta", "theta_tag"]

PathLike = Union[str, os.PathLike]

#: value columns of a positions file
POSITION_COLUMNS: tuple[str, ...] = ("x", "y", "z")


def read_metadata(path: PathLike, key: bytes) -> dict | None:
    """The JSON object stored under ``key`` in the file's schema metadata (None when absent)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    problem = input_problem(path)  # a folder, a FIFO (which would block the read), a device
    if problem is not None:
        raise InputError(os.fspath(path), "file", problem)
    try:
        md = pq.read_schema(os.fspath(path)).metadata or {}
    except (OSError, pa.ArrowInvalid) as exc:
        raise InputError(os.fspath(path), "file", f"not a readable Parquet file ({exc})") from None
    if key not in md:
        return None
    try:
        return json.loads(md[key])
    except ValueError as exc:
        raise InputError(os.fspath(path), f"metadata.{key.decode()}", f"not valid JSON ({exc})") from None


def theta_tag(theta: tuple[float, float]) -> str:
    """A file-name tag for a parameter pair, exact to 1e-6: ``sE0.950000_sR1.350000``."""
    return f"sE{theta[0]:.6f}_sR{theta[1]:.6f}"


def _meta_field(path, meta: dict, key: str):
    """One compared field of rollout metadata, checked for its type."""
    try:
        if key == "probe":
            value = meta["probe"]["name"]
            ok = isinstance(value, str)
        elif key == "n_frames":
            value = meta["probe"]["export"]["n_frames"]
            ok = isinstance(value, int)
        elif key == "n_particles":
            value = meta["n_gs"] + meta["n_fill"]
            ok = isinstance(meta["n_gs"], int) and isinstance(meta["n_fill"], int)
        elif key == "theta":
            value = tuple(float(t) for t in meta["theta"])
            ok = len(value) == 2 and all(math.isfinite(t) and t > 0 for t in value)
        else:
            value = meta[key]
            ok = isinstance(value, int) if key == "n_gs" else isinstance(value, str)
    except (KeyError, TypeError, ValueError):
        raise InputError(path, f"metadata.knockgs.{key}", "missing or malformed") from None
    if not ok:
        raise InputError(path, f"metadata.knockgs.{key}", f"malformed value {value!r}")
    return value


def _has_field(meta: dict, key: str) -> bool:
    try:
        _meta_field("", meta, key)
    except InputError:
        return False
    return True


def check_rollout_meta(path, meta: dict, *, partial: bool = False, **expected) -> None:
    """Check a rollout's metadata against its use; raise :class:`InputError` on a mismatch.

    ``expected`` may give ``object``, ``profile``, ``contract_hash``, ``theta`` (compared
    to 1e-6, the precision of :func:`theta_tag`), ``probe`` (the probe's name), ``n_gs``,
    ``n_particles`` (GS + fill) and ``n_frames`` (exported frames); None values are skipped.
    The error names the file and the metadata field, with both values. A field missing
    from the metadata is an error, or, with ``partial=True`` (a hand-made file that does
    not carry the simulator's metadata), not compared.
    """
    for key, want in expected.items():
        if want is None or (partial and not _has_field(meta, key)):
            continue
        got = _meta_field(path, meta, key)
        if key == "theta":
            same = theta_tag(got) == theta_tag(tuple(float(t) for t in want))
            got, want = theta_tag(got), theta_tag(want)
        else:
            same = got == want
        if not same:
            raise InputError(path, f"metadata.knockgs.{key}", f"is '{got}', expected '{want}' where the file is used")


def read_long_values(
    path: PathLike, columns: Sequence[str], *, particles: Iterable[int] | None = None, dense_ids: bool = False
) -> np.ndarray:
    """Read value ``columns`` of a long-format Parquet file into an array [T, N, C] (float32).

    Rows may come in any order; frames must be 0..T-1 without gaps and every frame must hold
    the same particle set, each particle once.

    Parameters
    ----------
    path:
        The Parquet file.
    columns:
        The value columns, in the order of the last axis (C = len(columns)).
    particles:
        Optional particle ids to keep (in ascending id order in the result).
    dense_ids:
        The particle ids must be exactly 0..N-1 (a rollout's: a particle's id is its index in the
        particle set), not any set of distinct integers (a measurement's tracks).

    Raises
    ------
    InputError
        Unreadable file, missing column, nulls, non-numeric or non-finite values, duplicate
        or missing (frame, particle) rows, unknown particle ids in ``particles``.
    """
    import pyarrow.parquet as pq

    source = os.fspath(path)
    problem = input_problem(source)
    if problem is not None:
        raise InputError(source, "file", problem)
    try:
        schema = pq.read_schema(source)
    except Exception as exc:
        raise InputError(source, "file", f"cannot read Parquet file: {exc}") from None
    wanted_cols = ("frame", "particle", *columns)
    for col in wanted_cols:
        if col not in schema.names:
            raise InputError(source, col, "missing column")
    try:
        with pq.ParquetFile(source) as pf:
            streamed = _read_canonical(pf, columns)
    except Exception as exc:  # a truncated or corrupted file: ArrowInvalid, OSError
        raise InputError(source, "file", f"cannot read Parquet file: {exc}") from None
    if streamed is not None:
        _check_finite(source, streamed, columns)
        return _subset(source, streamed, np.arange(streamed.shape[1]), particles)
    try:
        table = pq.read_table(source, columns=list(wanted_cols))
    except Exception as exc:  # a truncated or corrupted file: ArrowInvalid, OSError
        raise InputError(source, "file", f"cannot read Parquet file: {exc}") from None
    cols = {}
    for col in wanted_cols:
        arr = table.column(col)
        if arr.null_count:
            raise InputError(source, col, f"{arr.null_count} null values")
        values = arr.to_numpy()
        want_int = col in ("frame", "particle")
        ok = np.issubdtype(values.dtype, np.integer) if want_int else (
            np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)
        )
        if not ok:
            kind = "integers" if want_int else "real numbers"
            raise InputError(source, col, f"expected {kind}, got {arr.type}")
        cols[col] = values
    if table.num_rows == 0:
        raise InputError(source, "frame", "no rows")

    frame, particle = cols["frame"], cols["particle"]
    n_rows = frame.size
    # the canonical order (frame-major, particles 0..N-1 in every frame), as the writers lay
    # rows out, needs no sort and no further checks; compared in place, without index copies
    n_guess = int(particle.max()) + 1 if int(particle.min()) >= 0 else 0
    if n_guess and n_rows % n_guess == 0:
        n_t = n_rows // n_guess
        if (np.array_equal(particle.reshape(n_t, n_guess), np.broadcast_to(np.arange(n_guess), (n_t, n_guess)))
                and np.array_equal(frame.reshape(n_t, n_guess), np.broadcast_to(np.arange(n_t)[:, None], (n_t, n_guess)))):
            out = np.empty((n_t, n_guess, len(columns)), dtype=np.float32)
            for k, c in enumerate(columns):
                out[:, :, k] = cols[c].reshape(n_t, n_guess)
            _check_finite(source, out, columns)
            return _subset(source, out, np.arange(n_guess), particles)
    frame = frame.astype(np.int64)
    particle = particle.astype(np.int64)
    order = np.lexsort((particle, frame))
    frame, particle = frame[order], particle[order]
    values = np.stack([cols[c][order] for c in columns], axis=1).astype(np.float32)
    _check_finite(source, values, columns)

    frames, counts = np.unique(frame, return_counts=True)
    if frames[0] != 0 or not np.array_equal(frames, np.arange(frames.size)):
        missing = sorted(set(range(int(frames[-1]) + 1)) - set(frames.tolist()))
        detail = f"missing frame(s) {missing[:5]}" if missing else f"frames start at {frames[0]}"
        raise InputError(source, "frame", f"frames must be 0..T-1 without gaps: {detail}")
    if np.any(counts != counts[0]):
        t = int(frames[np.argmax(counts != counts[0])])
        raise InputError(
            source,
            "particle",
            f"frame {t} has {int(counts[frames == t][0])} rows, frame 0 has {int(counts[0])}: "
            "every frame needs the same particles",
        )
    n_t, n_p = frames.size, int(counts[0])
    ids = particle.reshape(n_t, n_p)
    dup = ids[:, 1:] == ids[:, :-1]
    if dup.any():
        t, j = np.argwhere(dup)[0]
        raise InputError(source, "particle", f"duplicate row for frame {int(t)}, particle {int(ids[t, j])}")
    differ = np.any(ids != ids[0], axis=1)
    if differ.any():
        t = int(np.argmax(differ))
        raise InputError(source, "particle", f"frame {t} holds a different particle set than frame 0")
    if dense_ids and not np.array_equal(ids[0], np.arange(n_p)):
        raise InputError(source, "particle", f"ids must be 0..{n_p - 1} (a particle's index in the particle set), "
                         f"got {int(ids[0, 0])}..{int(ids[0, -1])}")
    return _subset(source, values.reshape(n_t, n_p, len(columns)), ids[0], particles)


def _particles_per_frame(meta) -> int | None:
    """The particle count a file in the writers' canonical order has per frame, from the
    ``particle`` column's row-group statistics (its largest id + 1), or None where a row group
    has none."""
    j = meta.schema.names.index("particle")
    top = -1
    for g in range(meta.num_row_groups):
        stats = meta.row_group(g).column(j).statistics
        if stats is None or not stats.has_min_max:
            return None
        top = max(top, int(stats.max))
    return top + 1 if top >= 0 else None


def _read_canonical(pf, columns: Sequence[str]) -> np.ndarray | None:
    """The values [T, N, C] (float32) of a Parquet file ``pf`` whose rows are in the writers'
    canonical order (frame-major, particles 0..N-1 in every frame), read row group by row group
    into the result: at most one row group beside it in memory, not the whole table and its
    copies. None where the file is not so (another order, a gap, nulls, other types, no
    statistics): the caller's general path then reads it and names what is wrong. Finiteness
    is the caller's to check."""
    import pyarrow as pa

    meta = pf.metadata
    types = {f.name: f.type for f in pf.schema_arrow}
    if not all(pa.types.is_integer(types[k]) for k in ("frame", "particle")) or not all(
            pa.types.is_floating(types[c]) or pa.types.is_integer(types[c]) for c in columns):
        return None
    n_rows, n = meta.num_rows, _particles_per_frame(meta)
    if not n_rows or not n or n_rows % n:
        return None
    out = np.empty((n_rows // n, n, len(columns)), dtype=np.float32)
    flat = out.reshape(n_rows, len(columns))
    r0 = 0
    for g in range(meta.num_row_groups):
        t = pf.read_row_group(g, columns=["frame", "particle", *columns])
        if any(t.column(c).null_count for c in t.column_names):
            return None
        m = t.num_rows
        rows = np.arange(r0, r0 + m, dtype=np.int64)
        if not (np.array_equal(t.column("particle").to_numpy(), rows % n)
                and np.array_equal(t.column("frame").to_numpy(), rows // n)):
            return None
        for k, c in enumerate(columns):
            flat[r0:r0 + m, k] = t.column(c).to_numpy()
        r0 += m
    return out if r0 == n_rows else None


def _check_finite(source, values: np.ndarray, columns: Sequence[str]) -> None:
    """Raise naming the first of ``columns`` (the last axis of ``values``) with a non-finite value."""
    if np.isfinite(np.sum(values, dtype=np.float64)):  # exact: finite float32 values cannot overflow it
        return
    finite = np.isfinite(values).reshape(-1, len(columns)).all(axis=0)
    if not finite.all():
        raise InputError(source, columns[int(np.argmin(finite))], "non-finite values")


def _subset(source, out: np.ndarray, ids: np.ndarray, particles: Iterable[int] | None) -> np.ndarray:
    """``out`` [T, N, C] (particle ids ``ids`` [N], ascending) restricted to ``particles``."""
    if particles is None:
        return out
    wanted = np.unique(np.asarray(list(particles), dtype=np.int64))
    if wanted.size == 0:
        raise InputError(source, "particle", "empty particle subset")
    idx = np.searchsorted(ids, wanted)
    idx_c = np.clip(idx, 0, ids.size - 1)
    absent = ids[idx_c] != wanted
    if absent.any():
        raise InputError(source, "particle", f"particle ids not in the file: {wanted[absent][:5].tolist()}")
    return out[:, idx, :]


def read_positions(path: PathLike, *, particles: Iterable[int] | None = None) -> np.ndarray:
    """Positions [T, N, 3] (float32) of a long-format file (columns ``x``, ``y``, ``z``);
    see :func:`read_long_values`."""
    return read_long_values(path, POSITION_COLUMNS, particles=particles)
