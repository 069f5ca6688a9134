"""Atomic file output and JSON sanitizing: the one implementation every writer uses.

Every file the library writes goes through :func:`atomic_write`: the bytes land in a
temporary file beside the target (same directory, so the rename is atomic on POSIX), which
replaces the target only once it is complete. On any failure (an exception, a full disk,
an interrupt) the temporary file is removed and the previous file, if any, is left as it
was. A target that exists but is not a regular file (a directory, a device node, a FIFO) is
refused before anything is written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

from .errors import InputError

__all__ = [
    "atomic_write",
    "json_safe",
    "write_bytes",
    "write_json",
    "write_npz",
    "write_parquet",
    "write_text",
]


def json_safe(obj: Any) -> Any:
    """``obj`` as plain JSON types, recursively.

    Dataclass instances become dicts of their fields, mappings dicts with string keys,
    tuples and arrays lists, NumPy scalars Python scalars, paths strings. Non-finite floats
    follow one policy: NaN becomes ``None`` (JSON ``null``: no value), +-infinity the
    strings ``"inf"`` / ``"-inf"`` (a real, meaningful value, e.g. a sticky support's
    friction), so that the output is strict JSON (``allow_nan=False`` holds).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: json_safe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        if math.isfinite(value):
            return value
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def _check_target(path: Path) -> None:
    if path.exists() and not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file"
        raise InputError(path, "output", f"the output path is {kind}; refusing to replace it")


@contextlib.contextmanager
def atomic_write(path, *, mode: str = "wb", suffix: str | None = None) -> Iterator[IO]:
    """Open a temporary file for writing that replaces ``path`` on success.

    Parameters
    ----------
    path:
        The target file. Its parent directory is created.
    mode:
        ``"wb"`` (bytes) or ``"w"`` (text, UTF-8).
    suffix:
        The temporary file's suffix (default: the target's, so that writers that infer a
        format from the extension still work).

    Yields the open file object; on an exception the temporary file is removed, the target
    untouched, and the exception re-raised.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    _check_target(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{path.suffix if suffix is None else suffix}")
    try:
        with open(tmp, mode, **({"encoding": "utf-8", "newline": ""} if mode == "w" else {})) as fh:
            yield fh
            fh.flush()
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_write(path, mode="wb") as fh:
        fh.write(data)


def write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` atomically."""
    with atomic_write(path, mode="w") as fh:
        fh.write(text)


def write_json(path, obj: Any, *, indent: int | None = 2, sort_keys: bool = False) -> None:
    """Write ``json_safe(obj)`` as strict JSON (no NaN literals) plus a newline, atomically."""
    write_text(path, json.dumps(json_safe(obj), indent=indent, sort_keys=sort_keys, allow_nan=False) + "\n")


def write_parquet(path, table, *, compression: str = "zstd") -> None:
    """Write a ``pyarrow.Table`` to ``path`` atomically."""
    import pyarrow.parquet as pq

    with atomic_write(path, mode="wb") as fh:
        pq.write_table(table, fh, compression=compression)


def write_npz(path, *, compressed: bool = True, **arrays) -> None:
    """Write arrays to an ``.npz`` file atomically (``np.savez_compressed`` by default)."""
    with atomic_write(path, mode="wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)
