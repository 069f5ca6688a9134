"""Atomic file output and JSON sanitizing: the one implementation every writer uses.

Every file the library writes goes through :func:`atomic_write`: the bytes land in a
temporary file beside the target (same directory, so the rename is atomic on POSIX), which
replaces the target only once it is complete. On any failure (an exception, a full disk,
an interrupt) the temporary file is removed and the previous file, if any, is left as it
was. A target that exists but is not a regular file (a directory, a device node, a FIFO) is
refused before anything is written.

Commands check all their output paths at once, before any work, with
:func:`check_outputs`: an output is never one of the command's inputs or another of its
outputs, never an existing non-regular file (nor an existing file where a folder is
expected), and its folder is writable. :func:`check_output` is the per-path part of that
check, the one :func:`atomic_write` applies to every file it writes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from ..errors import InputError

__all__ = [
    "StagedFolders",
    "atomic_write",
    "check_files_in",
    "check_folder_outputs",
    "check_job_inputs",
    "check_output",
    "check_outputs",
    "json_safe",
    "remove_outputs",
    "staged_folders",
    "staging_folder",
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


def _name_max(path: Path) -> int:
    """The longest file name [bytes] the folder of ``path`` (its nearest existing one) takes."""
    try:
        return os.pathconf(_nearest_existing(path.parent), "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        return 255


def _temp_path(path: Path, suffix: str) -> Path:
    """The temporary file :func:`atomic_write` writes beside ``path``: ``.NAME.tmpPID`` + suffix,
    with NAME shortened (and marked by a hash of the whole name) where the whole would exceed the
    name-length limit that NAME itself fits in."""
    import hashlib

    tail = f".tmp{os.getpid()}{suffix}"
    name = f".{path.name}{tail}"
    limit = _name_max(path)
    if len(os.fsencode(name)) <= limit:
        return path.with_name(name)
    digest = hashlib.sha256(os.fsencode(path.name)).hexdigest()[:12]
    keep = os.fsencode(path.name)[: max(0, limit - len(os.fsencode(tail)) - len(digest) - 2)]
    return path.with_name(f".{keep.decode('utf-8', 'ignore')}~{digest}{tail}")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def check_output(path, field: str = "output", *, directory: bool = False) -> None:
    """Refuse an output path that cannot be written without destroying something else.

    ``path`` may not exist yet. If it exists it must be a regular file (``directory=True``:
    a folder); an existing directory, device node, FIFO or socket is never replaced, and neither
    is a symbolic link to a file (the link would be replaced, not the file it points to). A path
    written with a trailing slash names a folder: refused where a file is written. The file name
    must fit the folder's name-length limit. The nearest existing ancestor must be a writable
    folder (missing folders are created by the writer). Raises
    :class:`~knockgs_core.errors.InputError` naming the path and ``field``.
    """
    raw = os.fspath(path)
    if not directory and raw.endswith((os.sep, "/")):
        raise InputError(raw, field, "ends with '/', which names a folder, but a file is written here")
    path = Path(path)
    if len(os.fsencode(path.name)) > _name_max(path):
        raise InputError(path, field, f"the file name is {len(os.fsencode(path.name))} bytes, more than the "
                         f"{_name_max(path)} a name may have here")
    if os.path.lexists(path) and not os.path.exists(path):
        raise InputError(path, field, "is a broken symbolic link; refusing to write through it")
    if path.exists():
        if directory:
            if not path.is_dir():
                raise InputError(path, field, "exists and is not a folder (a folder is written here)")
        elif path.is_dir():
            raise InputError(path, field, "the output path is a directory; refusing to replace it")
        elif not path.is_file():
            raise InputError(path, field, "the output path is not a regular file (a device, FIFO or socket); "
                                          "refusing to replace it")
    if not directory and os.path.islink(path):
        raise InputError(path, field, f"is a symbolic link (to {os.readlink(path)}); writing would replace the link, "
                         "not its target: refusing (give the target's path, or remove the link)")
    parent = _nearest_existing(path.parent if not (directory and path.is_dir()) else path)
    if not parent.is_dir():
        raise InputError(path, field, f"'{parent}' is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(path, field, f"folder '{parent}' is not writable")


def _same(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(
    outputs: Mapping[str, Any],
    inputs: Mapping[str, Any] = {},  # noqa: B006 (read only)
    *,
    directories: Mapping[str, Sequence[str]] = {},  # noqa: B006 (read only)
) -> None:
    """Check a command's output paths before it does any work.

    Parameters
    ----------
    outputs:
        field (e.g. ``"--output"``) -> output path (None entries are skipped). Fields named
        in ``directories`` are folders; the others files.
    inputs:
        field -> input path, or a list of paths (None entries skipped): no output may be
        one of them (same path, a symbolic or hard link to it).
    directories:
        folder field -> the file-name patterns the command writes inside it (glob syntax);
        an input inside the folder matching one of them is refused too.

    Every output passes :func:`check_output`, no two outputs are the same file and no
    output is an input. Raises :class:`~knockgs_core.errors.InputError` naming the path
    and the field.
    """
    import fnmatch

    def flat(mapping):
        for field, value in mapping.items():
            if value is None:
                continue
            for v in (value if isinstance(value, (list, tuple)) else [value]):
                if v is not None:
                    yield field, Path(v)

    for field, value in outputs.items():  # a trailing slash (dropped by Path) names a folder
        if field not in directories:
            for v in (value if isinstance(value, (list, tuple)) else [value]):
                if v is not None and os.fspath(v).endswith((os.sep, "/")):
                    check_output(v, field)
    outs = list(flat(outputs))
    ins = list(flat(inputs))
    for i, (field, path) in enumerate(outs):
        is_dir = field in directories
        for other_field, other in outs[:i]:
            if _same(path, other):
                raise InputError(path, field, f"is also the {other_field} output of the command")
        for in_field, src in ins:
            if _same(path, src):
                raise InputError(path, field, f"would overwrite the {in_field} input of the command")
            if is_dir and _same(src.parent, path) and any(fnmatch.fnmatch(src.name, pat) for pat in directories[field]):
                raise InputError(path, field, f"writing {src.name} in this folder would overwrite the "
                                              f"{in_field} input of the command")
        check_output(path, field, directory=is_dir)


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
    check_output(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path(path, path.suffix if suffix is None else suffix)
    try:
        with open(tmp, mode, **({"encoding": "utf-8", "newline": ""} if mode == "w" else {})) as fh:
            yield fh
            fh.flush()
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            exc.filename = str(path)  # a failed write (e.g. a full disk) names the file it was for
        raise


def remove_outputs(*paths, log: IO | None = None) -> None:
    """Remove ``paths`` (a failed job's output files or folders) where they exist, each
    removal reported to ``log`` as ``removed the partial output PATH``."""
    import shutil

    for path in map(Path, paths):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists() or path.is_symlink():
            with contextlib.suppress(OSError):
                path.unlink()
        else:
            continue
        if log is not None:
            print(f"removed the partial output {path}", file=log, flush=True)


def staging_folder(folder) -> Path:
    """The hidden sibling in which :func:`staged_folders` builds ``folder``: ``.NAME.partial``."""
    folder = Path(folder)
    return folder.with_name(f".{folder.name}.partial")


class StagedFolders(list):
    """The folders a job writes its files into, one for each output folder it was made with,
    in that order (a list of paths), and the map of the job's files into them
    (:meth:`path`). :func:`staged_folders` yields one whose folders are staging folders; made
    with the output folders themselves, it writes in place."""

    def __init__(self, folders: Sequence, writes_into: Sequence):
        super().__init__(Path(f) for f in writes_into)
        self._into = dict(zip((Path(f) for f in folders), self))

    def path(self, path) -> Path | None:
        """``path``, a file directly in one of the output folders, in the folder it is written
        into (the same name); None stays None. A path elsewhere is refused as
        :func:`check_files_in` refuses it (a job checks all its files so before it starts)."""
        if path is None:
            return None
        path = Path(path)
        check_files_in([path], self._into, source="staged folders")
        return self._into[path.parent] / path.name


def check_files_in(files, folders, *, source: str) -> None:
    """Raise an :class:`InputError` of ``source``'s field ``output`` naming the first of
    ``files`` (paths; None entries are skipped) that does not lie directly in one of
    ``folders``: a job's files must be in its output folders, where :func:`staged_folders`
    builds them."""
    folders = [Path(f) for f in folders]
    for f in files:
        if f is not None and Path(f).parent not in folders:
            raise InputError(source, "output", f"{f} lies outside the job's output folders "
                             f"({', '.join(str(d) for d in dict.fromkeys(folders))})")


def check_folder_outputs(files, *, field: str = "file") -> None:
    """Refuse a read of files that were removed from a finished job's output folder.

    A job's output folder is whole when the job ends (:func:`staged_folders`); a file removed
    from it afterwards is not noticed by Snakemake, which tracks the folder, not its files.
    The job that reads the folder checks, before any work, that every file it will read from
    it is there.

    Parameters
    ----------
    files:
        The paths the reader will read (None entries are skipped), or a mapping field (the
        reader's parameter that names them) -> such paths.
    field:
        The field of ``files`` when it is not a mapping.

    Raises an :class:`~knockgs_core.errors.InputError` naming the first missing file whose
    folder exists, how many are missing, and the command that remakes the folders:
    ``snakemake --cores 1 --force FOLDER ...`` (Snakemake then also reruns what reads them, as
    they are newer). A missing file whose folder is missing too is not refused: the folder is
    the workflow's missing output, which Snakemake makes.
    """
    named = files.items() if isinstance(files, Mapping) else [(field, files)]
    read, missing = 0, []
    for name, paths in named:
        for f in paths:
            if f is None:
                continue
            read += 1
            if not os.path.lexists(f) and os.path.isdir(os.path.dirname(f) or "."):
                missing.append((name, os.fspath(f)))
    if missing:
        name, first = missing[0]
        folders = " ".join(dict.fromkeys(os.path.dirname(f) or "." for _, f in missing))
        raise InputError(first, name, f"missing from its folder, a finished job's output (removed after the job "
                                      f"ended; {len(missing)} of the {read} files read from such folders "
                                      f"{'is' if len(missing) == 1 else 'are'} missing); remake the folder, with the "
                                      f"run's --configfile/--config options: snakemake --cores 1 --force {folders}")


def _strings(value) -> Iterable[str]:
    """Every string in ``value`` (a string, or mappings and sequences of them, nested)."""
    if isinstance(value, (str, os.PathLike)):
        yield os.fspath(value)
    elif isinstance(value, Mapping):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _strings(v)


def check_job_inputs(job, *, log: IO | None = None) -> None:
    """The input check of a workflow job, before any work: every file that its parameters
    name directly in one of its input folders (the finished output folder of another job) is
    there (:func:`check_folder_outputs`, each file's field the parameter naming it).

    ``job``: the ``snakemake`` object of a workflow script (its ``input`` and named
    ``params``). A refusal is one line ``knockgs workflow: error: ...`` in ``log`` (default:
    ``sys.stderr``, the job's log) and on the run's console (``sys.__stderr__``), and the job
    exits with status 2, without a traceback.
    """
    folders = {os.path.normpath(f) for f in _strings(list(job.input)) if os.path.isdir(f)}
    files: dict[str, list[str]] = {}
    for name, value in job.params.items():
        for path in _strings(value):
            if os.path.dirname(path) and os.path.normpath(os.path.dirname(path)) in folders:
                files.setdefault(name, []).append(path)
    try:
        check_folder_outputs(files)
    except InputError as exc:
        line = f"knockgs workflow: error: {' '.join(str(exc).split())}"
        for out in dict.fromkeys((log or sys.stderr, sys.__stderr__)):
            if out is not None:
                print(line, file=out, flush=True)
        raise SystemExit(2) from None


@contextlib.contextmanager
def staged_folders(*folders, log: IO | None = None) -> Iterator[StagedFolders]:
    """Build a job's output folders under hidden names and move them into place at the end.

    Parameters
    ----------
    folders:
        The job's output folders (a folder named twice is built once).
    log:
        Where the removal of a stale or failed staging folder is reported.

    Yields the staging folders (:func:`staging_folder`), one for each of ``folders``, created
    empty, as a :class:`StagedFolders` (its :meth:`~StagedFolders.path` maps a file of an
    output folder into its staging folder); a staging folder left by an earlier attempt that was
    killed is removed first. When
    the block ends without error each is renamed onto its folder (a folder already there, an
    older output of the same job, is removed just before); when it raises or is interrupted
    (``KeyboardInterrupt`` included) the staging folders are removed and the exception
    re-raised. So an output folder appears whole or not at all, whatever stops the job and
    when: an uncaught SIGTERM (a batch system's time limit) or SIGKILL runs no clean-up in
    the job, and a workflow manager stopped at the same time may record the job as finished
    before it removes the job's outputs; a resumed run then finds the folder missing and
    redoes the job.
    """
    import shutil

    finals = list(dict.fromkeys(Path(f) for f in folders))
    stages = {final: staging_folder(final) for final in finals}
    for final, stage in stages.items():
        check_output(final, directory=True)
        check_output(stage, directory=True)
        if os.path.lexists(stage):
            remove_outputs(stage, log=log)  # an earlier attempt's, killed before its end
        stage.mkdir(parents=True)
    try:
        yield StagedFolders(folders, [stages[Path(f)] for f in folders])
    except BaseException:
        remove_outputs(*stages.values(), log=log)
        raise
    for final, stage in stages.items():
        if final.is_dir():
            shutil.rmtree(final)
        os.rename(stage, final)


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


def write_parquet(path, table, *, compression: str = "zstd", column_encoding: dict[str, str] | None = None) -> None:
    """Write a ``pyarrow.Table`` to ``path`` atomically. ``column_encoding`` (column name ->
    Parquet encoding) switches dictionary encoding off for the whole file."""
    import pyarrow.parquet as pq

    kw = {} if column_encoding is None else {"use_dictionary": False, "column_encoding": column_encoding}
    with atomic_write(path, mode="wb") as fh:
        pq.write_table(table, fh, compression=compression, **kw)


def write_npz(path, *, compressed: bool = True, **arrays) -> None:
    """Write arrays to an ``.npz`` file atomically (``np.savez_compressed`` by default)."""
    with atomic_write(path, mode="wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)
