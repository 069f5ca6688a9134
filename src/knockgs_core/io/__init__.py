"""The file layer: crash-safe writes, output checks, and the long Parquet format of rollouts.

Every file KnockGS writes goes through :func:`atomic_write` (or a ``write_*`` built on it): the
bytes land in a temporary file beside the target, which replaces it only once complete, so a
failed write leaves the old file and no temporary one. Commands check all their outputs before
any work (:func:`check_outputs`), and all their input paths too (:func:`check_inputs`: a FIFO, a
device or a folder where a file is read is refused before it is opened); a job's output folders
are built under hidden names and moved into place once complete (:func:`staged_folders`), and
the job that reads one checks that no file it reads was removed from it since
(:func:`check_folder_outputs`, :func:`check_job_inputs`).

Rollouts and deformation gradients are *long-format* Parquet files: one row per (frame,
particle), integer keys ``frame`` and ``particle`` and float32 value columns (``x, y, z``;
``F00`` .. ``F22``). :func:`read_long_values` reads them into ``(n_frames, n_particles,
n_columns)`` arrays, :func:`long_table` and :class:`LongFormatStream` write them (whole, or frame
by frame while a rollout runs).
"""

from ._files import (
    StagedFolders,
    atomic_write,
    check_files_in,
    check_folder_outputs,
    check_job_inputs,
    check_output,
    check_outputs,
    json_safe,
    remove_outputs,
    staged_folders,
    staging_folder,
    write_bytes,
    write_json,
    write_npz,
    write_parquet,
    write_text,
)
from ._inputs import INPUT_LIMITS, check_input, check_inputs, input_problem
from ._long_format import (
    POSITION_COLUMNS,
    check_rollout_meta,
    read_long_values,
    read_metadata,
    read_positions,
    theta_tag,
)
from ._long_writer import GROUP_ROWS, LONG_COMPRESSION, LongFormatStream, long_encoding, long_table
from ._threads import ordered_map

__all__ = [
    "GROUP_ROWS",
    "INPUT_LIMITS",
    "LONG_COMPRESSION",
    "POSITION_COLUMNS",
    "LongFormatStream",
    "StagedFolders",
    "atomic_write",
    "check_files_in",
    "check_folder_outputs",
    "check_input",
    "check_inputs",
    "check_job_inputs",
    "check_output",
    "check_outputs",
    "check_rollout_meta",
    "input_problem",
    "json_safe",
    "long_encoding",
    "long_table",
    "ordered_map",
    "read_long_values",
    "read_metadata",
    "read_positions",
    "remove_outputs",
    "staged_folders",
    "staging_folder",
    "theta_tag",
    "write_bytes",
    "write_json",
    "write_npz",
    "write_parquet",
    "write_text",
]
