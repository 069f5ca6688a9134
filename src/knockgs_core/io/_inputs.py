"""Input paths checked before any work: the counterpart of :func:`check_outputs` (private).

A path a command or a reader is given is checked without opening it for reading first: it
exists, it is a regular file (or the folder the option expects), it is readable, and its size
is within the bound of its kind (:data:`INPUT_LIMITS`). So a FIFO never blocks a reader, a
device such as ``/dev/zero`` is never read until memory runs out, a folder given as a file is
named as a folder, and the message says what the path is instead of what was expected.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from pathlib import Path

from ..errors import InputError

__all__ = ["INPUT_LIMITS", "check_input", "check_inputs", "input_problem"]

_MiB = 1 << 20

#: bytes an input of a kind may have at most: text read whole into a parser (a contract's or the
#: workflow config's YAML: 4 MiB, a JSON row or estimate: 64 MiB; the shipped ones are < 20 KB),
#: and every other file (tables, Parquet, .npz, PLY) at most the machine's physical memory, which
#: its arrays could not be held in anyway (None: that bound, read when checked)
INPUT_LIMITS: dict[str, int | None] = {"yaml": 4 * _MiB, "json": 64 * _MiB, "data": None}

_KIND_OF_SUFFIX = {".yaml": "yaml", ".yml": "yaml", ".json": "json"}


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX: no bound
        return None


def _what(mode: int) -> str:
    """What a non-regular file is, in words."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _size(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("KB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def input_problem(path, *, folder: bool = False, kind: str | None = None) -> str | None:
    """What is wrong with ``path`` as an input, in words, or None when it may be read.

    ``folder``: a folder is expected (readable and searchable), else a regular file of ``kind``
    (a key of :data:`INPUT_LIMITS`; default from the suffix: ``.yaml``/``.yml``, ``.json``,
    else ``data``) within that kind's size bound. A symbolic link is judged by its target.
    Only ``stat`` and, for a regular file or a folder, an open are used: nothing blocks.
    """
    p = os.fspath(path)
    if p == "":
        return "is an empty path"
    try:
        st = os.stat(p)
    except FileNotFoundError:
        if os.path.lexists(p):
            return f"is a broken symbolic link (to {os.readlink(p)})"
        parent = os.path.dirname(os.path.abspath(p))
        return "does not exist" + ("" if os.path.isdir(parent) else f" (no folder {parent})")
    except NotADirectoryError:
        return "does not exist (a part of the path above it is a file, not a folder)"
    except OSError as exc:
        return f"cannot be examined ({exc.strerror or exc})"
    if folder:
        if not stat.S_ISDIR(st.st_mode):
            kind_of = "a regular file" if stat.S_ISREG(st.st_mode) else _what(st.st_mode)
            return f"is {kind_of}, not a folder"
        if not os.access(p, os.R_OK | os.X_OK):
            return "is a folder that cannot be read (permission denied)"
        return None
    if not stat.S_ISREG(st.st_mode):
        return f"is {_what(st.st_mode)}, not a regular file"
    kind = kind or _KIND_OF_SUFFIX.get(os.path.splitext(p)[1].lower(), "data")
    limit = INPUT_LIMITS[kind] if kind in INPUT_LIMITS else INPUT_LIMITS["data"]
    what = f"a {kind} input" if limit is not None else "an input"
    if limit is None:
        limit, what = _physical_memory(), "an input (the machine's physical memory)"
    if limit is not None and st.st_size > limit:
        return f"is {_size(st.st_size)}, more than {what} may be ({_size(limit)})"
    try:
        with open(p, "rb"):
            pass
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    return None


def check_input(path, field: str = "input", *, folder: bool = False, kind: str | None = None) -> Path:
    """Refuse an input path that cannot be read as expected (:func:`input_problem`), naming the
    path and ``field``; returns the path."""
    problem = input_problem(path, folder=folder, kind=kind)
    if problem is not None:
        raise InputError(os.fspath(path), field, problem)
    return Path(path)


def check_inputs(inputs: Mapping[str, object], *, folders: tuple[str, ...] = ()) -> None:
    """Check all of a command's input paths before any work.

    Parameters
    ----------
    inputs:
        field (e.g. ``"--library"``) -> path, or a list of paths (None entries are skipped).
    folders:
        the fields whose paths are folders; every other path is a file.

    Raises :class:`~knockgs_core.errors.InputError` naming the first bad path and its field.
    """
    for field, value in inputs.items():
        for v in (value if isinstance(value, (list, tuple)) else [value]):
            if v is not None:
                check_input(v, field, folder=field in folders)
