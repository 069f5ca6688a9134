"""Writing the long Parquet format: whole tables, or frame by frame while a rollout runs.

A long-format file has one row per (frame, particle), frame-major and particles ascending in
every frame (the order :func:`knockgs_core._long_format.read_long_values` reads without a
sort): integer keys ``frame``, ``particle`` (int32) and float32 value columns. Every writer
uses one codec and one set of encodings (:data:`LONG_COMPRESSION`, :func:`long_encoding`),
so a file written frame by frame (:class:`LongFormatStream`) decodes to exactly the values
and metadata of the same frames written at once (:func:`long_table`).
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ._files import atomic_write, check_output
from ..errors import InputError

__all__ = ["LONG_COMPRESSION", "GROUP_ROWS", "long_encoding", "long_table", "LongFormatStream"]

#: codec of the long-format files: LZ4 writes a paper-scale rollout about 4x faster than zstd's
#: default (benchmarks/results/2026-11-25-rollout-writing.md), in a file a third smaller thanks to the encodings
LONG_COMPRESSION = "lz4"

#: a streamed file's frames go out in row groups of at least this many rows (a paper-scale
#: frame of ~700k particles is a group of its own; a small CPU rollout's frames a few a group)
GROUP_ROWS = 1 << 16

#: whether pyarrow can set a file's key-value metadata after its row groups (pyarrow >= 17);
#: without it a stream keeps its frames and writes the file whole when it is finished
CAN_STREAM = hasattr(pq.ParquetWriter, "add_key_value_metadata")

_KEYS = ("frame", "particle")


def long_encoding(columns: Sequence[str]) -> dict[str, str]:
    """Parquet encodings of a long-format table's ``columns``: the integer keys (``frame``
    runs, ``particle`` counts up) as deltas, the float32 values split by byte (exponents and
    high mantissa bytes compress), no dictionaries (a particle index is unique in its frame)."""
    return {name: "DELTA_BINARY_PACKED" if name in _KEYS else "BYTE_STREAM_SPLIT" for name in columns}


def long_table(values: np.ndarray, columns: Sequence[str], *, first_frame: int = 0) -> pa.Table:
    """The long-format table of ``values`` [T, N, C] (C = len(columns)): frames
    ``first_frame .. first_frame + T - 1``, particles 0 .. N-1 in each, value column c from
    ``values[:, :, c]`` as float32."""
    T, N, C = values.shape
    if C != len(columns):
        raise ValueError(f"{C} value columns, {len(columns)} names")
    cols = {"frame": pa.array(np.repeat(np.arange(first_frame, first_frame + T, dtype=np.int32), N)),
            "particle": pa.array(np.tile(np.arange(N, dtype=np.int32), T))}
    for c, name in enumerate(columns):
        cols[name] = pa.array(np.ascontiguousarray(values[:, :, c], dtype=np.float32).reshape(-1))
    return pa.table(cols)


def _schema(columns: Sequence[str]) -> pa.Schema:
    return pa.schema([(k, pa.int32()) for k in _KEYS] + [(name, pa.float32()) for name in columns])


class _Aborted(Exception):
    """The stream was aborted (or the program ended before it was finished): no file."""


class _Finish:
    def __init__(self, metadata: dict[bytes, bytes]):
        self.metadata = metadata


_ABORT = object()


class LongFormatStream:
    """A long-format Parquet file written frame by frame on a thread of its own.

    The caller hands frames over in order with :meth:`put` (frame 0 first, each once) and
    ends with :meth:`finish` (the schema metadata, e.g. the rollout's, only known at the end)
    or :meth:`abort`; :meth:`wait` waits for the file. The thread appends the frames as row
    groups (at least ``group_rows`` rows each) while the caller computes the next ones, so
    that once the last frame is handed over only it and the footer remain to be written.
    The file holds the same rows in the same order (frame-major, particles ascending), with
    the same codec, encodings and metadata, as :func:`long_table` of all the frames written
    at once; it is written atomically (:func:`knockgs_core._io.atomic_write`): it appears
    under ``path`` only once complete, and an abort, a failure or the program's end before
    :meth:`finish` leaves neither it nor a temporary file.

    Parameters
    ----------
    path:
        The file.
    columns:
        The value columns' names (C).
    group_rows:
        The fewest rows of a row group (the last may hold fewer).
    refuse_non_finite:
        What the values are (e.g. ``"positions"``): a non-finite value then fails the write
        with :class:`~knockgs_core.errors.InputError` naming the file and the first column;
        None writes them as they come.
    """

    def __init__(self, path, columns: Sequence[str], *, group_rows: int = GROUP_ROWS,
                 refuse_non_finite: str | None = None):
        if isinstance(group_rows, bool) or not isinstance(group_rows, int) or group_rows < 1:
            raise InputError(path, "group_rows", f"must be an integer >= 1, got {group_rows!r}")
        check_output(path)  # a folder or a device in the way is refused now, not at the first frame
        self.path = Path(path)
        self.columns = tuple(columns)
        self.group_rows = group_rows
        self.refuse_non_finite = refuse_non_finite
        self.frames = 0  # handed over so far
        self.finished = False
        self._n: int | None = None
        self._aborted = threading.Event()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"long-writer {self.path.name}")
        self._thread.start()

    # -- the caller's side ----------------------------------------------------------
    def put(self, frame: int, values: np.ndarray) -> None:
        """Hand frame ``frame`` over: ``values`` [N, C] float32, row i particle i. The array
        is kept, not copied, until written: the caller must not change it afterwards. Raises
        the write's error if it has failed already."""
        self._raise_failure()
        if self.finished or self._aborted.is_set():
            raise InputError(self.path, "frame", f"frame {frame} handed over after the stream was closed")
        if frame != self.frames:
            raise InputError(self.path, "frame", f"frame {frame} handed over where frame {self.frames} was due "
                                                 "(frames come in order, each once)")
        values = np.asarray(values, dtype=np.float32)
        n = self._n if self._n is not None else values.shape[0] if values.ndim == 2 else -1
        if values.shape != (n, len(self.columns)):
            raise InputError(self.path, "particle", f"frame {frame} has shape {values.shape}, expected "
                                                    f"({'N' if n < 0 else n}, {len(self.columns)})")
        self._n = n
        self.frames += 1
        self._queue.put((frame, values))

    def finish(self, metadata: Mapping[bytes, bytes], *, n_frames: int | None = None) -> None:
        """No more frames: the file gets the schema ``metadata`` and is closed and renamed on
        the thread (:meth:`wait` waits for it). With ``n_frames``, the frames handed over
        must be that many; otherwise, as with none at all, the stream is aborted and
        :class:`~knockgs_core.errors.InputError` raised."""
        self._raise_failure()
        if self.finished or self._aborted.is_set():
            raise InputError(self.path, "frame", "the stream was closed already")
        if self.frames < 1 or (n_frames is not None and self.frames != n_frames):
            self.abort()
            raise InputError(self.path, "frame", f"{self.frames} frames handed over, expected "
                                                 f"{'at least 1' if n_frames is None else n_frames}")
        self.finished = True
        self._queue.put(_Finish(dict(metadata)))

    def abort(self) -> None:
        """Stop: the frames not written yet are dropped and the temporary file removed; returns
        once the thread has stopped. A file already complete and renamed stays."""
        self._aborted.set()
        self._queue.put(_ABORT)
        self._thread.join()

    @property
    def aborted(self) -> bool:
        """Whether :meth:`abort` was called."""
        return self._aborted.is_set()

    @property
    def done(self) -> bool:
        """Whether the thread has stopped (the file complete, the write failed or aborted)."""
        return not self._thread.is_alive()

    def wait(self) -> None:
        """Wait until the file is complete; raise the write's error, if any."""
        if not (self.finished or self._aborted.is_set()):
            raise InputError(self.path, "frame", "waited for before it was finished or aborted")
        self._thread.join()
        self._raise_failure()

    def _raise_failure(self) -> None:
        if self._error is not None:
            raise self._error

    # -- the writer thread -------------------------------------------------------------
    def _run(self) -> None:
        try:
            first = self._next()
            with atomic_write(self.path) as fh:
                (self._stream if CAN_STREAM else self._whole)(fh, first)
        except _Aborted:
            pass
        except BaseException as exc:  # raised to the caller by put, finish or wait
            self._error = exc

    def _next(self):
        """The next frame (or the finish); raises :class:`_Aborted` on an abort, or when the
        program's main thread has ended without finishing the stream."""
        while True:
            if self._aborted.is_set():
                raise _Aborted
            try:
                item = self._queue.get(timeout=1.0)
            except queue.Empty:
                if not threading.main_thread().is_alive():
                    raise _Aborted from None
                continue
            if item is _ABORT:
                raise _Aborted
            return item

    def _stream(self, fh, item) -> None:
        """Append the frames as row groups as they come; the metadata goes into the footer."""
        writer = pq.ParquetWriter(fh, _schema(self.columns), compression=LONG_COMPRESSION, use_dictionary=False,
                                  column_encoding=long_encoding(_KEYS + self.columns),
                                  store_schema=False)  # the footer's key-value metadata is then the schema's
        try:
            group: list[tuple[int, np.ndarray]] = []
            while not isinstance(item, _Finish):
                group.append(item)
                if len(group) * self._n >= self.group_rows:
                    writer.write_table(self._table(group))
                    group = []
                item = self._next()
            if group:
                writer.write_table(self._table(group))
            writer.add_key_value_metadata(item.metadata)
        except BaseException:
            with contextlib.suppress(Exception):
                writer.close()  # the temporary file goes; a writer left open would write to a closed file
            raise
        writer.close()

    def _whole(self, fh, item) -> None:
        """Without :data:`CAN_STREAM`: keep the frames, write the file whole at the finish."""
        group = []
        while not isinstance(item, _Finish):
            group.append(item)
            item = self._next()
        table = self._table(group).replace_schema_metadata(item.metadata)
        pq.write_table(table, fh, compression=LONG_COMPRESSION, use_dictionary=False,
                       column_encoding=long_encoding(table.column_names))

    def _table(self, group: list[tuple[int, np.ndarray]]) -> pa.Table:
        """The rows of consecutive frames ``group`` [(frame, values [N, C])]."""
        if self._aborted.is_set():
            raise _Aborted
        values = np.stack([v for _, v in group])
        if self.refuse_non_finite and not np.all(np.isfinite(values)):
            raise InputError(self.path, self.columns[0], f"refusing to write non-finite {self.refuse_non_finite}")
        return long_table(values, self.columns, first_frame=group[0][0])
