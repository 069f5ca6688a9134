"""The one atomic writer and JSON sanitizer (knockgs_core.io), and the library writers on it."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import knockgs_core.io._files as _io
from knockgs_core.io import atomic_write, json_safe, write_bytes, write_json, write_npz, write_parquet, write_text
from knockgs_core.errors import InputError


def _temp_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


def test_a_failing_writer_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "table.csv"
    write_text(target, "old\n")
    with pytest.raises(RuntimeError, match="disk full"):
        with atomic_write(target, mode="w") as fh:
            fh.write("new, half written")
            raise RuntimeError("disk full")
    assert target.read_text() == "old\n"
    assert _temp_files(tmp_path) == []


def test_an_interrupted_writer_leaves_nothing_new(tmp_path):
    target = tmp_path / "new.bin"
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(target) as fh:
            fh.write(b"\x00" * 100)
            raise KeyboardInterrupt
    assert not target.exists() and _temp_files(tmp_path) == []


def test_a_failing_rename_leaves_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "est.json"
    write_json(target, {"a": 1})
    before = target.read_bytes()

    def refuse(src, dst):
        raise OSError("read-only file system")

    monkeypatch.setattr(_io.os, "replace", refuse)
    with pytest.raises(OSError, match="read-only"):
        write_json(target, {"a": 2})
    assert target.read_bytes() == before and _temp_files(tmp_path) == []


@pytest.mark.parametrize("writer", [
    lambda p: write_text(p, "x"),
    lambda p: write_bytes(p, b"x"),
    lambda p: write_json(p, {}),
    lambda p: write_npz(p, a=np.zeros(2)),
])
def test_a_directory_is_refused(tmp_path, writer):
    folder = tmp_path / "out.csv"
    folder.mkdir()
    with pytest.raises(InputError, match="directory"):
        writer(folder)
    assert folder.is_dir() and list(folder.iterdir()) == []


@pytest.mark.skipif(not os.path.exists(os.devnull) or os.name == "nt", reason="needs a device node")
def test_a_device_is_refused():
    with pytest.raises(InputError, match="not a regular file"):
        write_text(os.devnull, "x")


def test_the_parent_folder_is_created_and_the_bytes_land(tmp_path):
    target = tmp_path / "a" / "b" / "c.txt"
    write_text(target, "line 1\nline 2\n")
    assert target.read_bytes() == b"line 1\nline 2\n"  # no newline translation


def test_parquet_and_npz_writers_round_trip(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table({"frame": pa.array([0, 1], pa.int32()), "x": pa.array([0.5, 1.5], pa.float32())})
    write_parquet(tmp_path / "r.parquet", table)
    assert pq.read_table(tmp_path / "r.parquet").equals(table)
    write_npz(tmp_path / "s.npz", mask=np.array([True, False]))
    with np.load(tmp_path / "s.npz") as z:
        assert z["mask"].tolist() == [True, False]


@dataclasses.dataclass(frozen=True)
class _Point:
    x: float
    tags: tuple


def test_json_safe_policy():
    doc = {
        "nan": math.nan, "inf": math.inf, "minus_inf": -math.inf, "f32": np.float32(0.5), "i64": np.int64(3),
        "flag": np.bool_(True), "array": np.array([1.0, np.nan]), "tuple": (1, 2), "path": Path("a") / "b.csv",
        "point": _Point(1.0, ("u", np.inf)), 7: "int key",
    }
    out = json_safe(doc)
    assert out == {
        "nan": None, "inf": "inf", "minus_inf": "-inf", "f32": 0.5, "i64": 3, "flag": True, "array": [1.0, None],
        "tuple": [1, 2], "path": os.path.join("a", "b.csv"), "point": {"x": 1.0, "tags": ["u", "inf"]}, "7": "int key",
    }
    assert type(out["flag"]) is bool and type(out["i64"]) is int and type(out["f32"]) is float
    json.dumps(out, allow_nan=False)  # strict JSON


def test_write_json_is_strict_json_with_a_final_newline(tmp_path):
    write_json(tmp_path / "e.json", {"value": math.nan, "scale": np.float64(2.0)}, indent=1)
    text = (tmp_path / "e.json").read_text()
    assert text.endswith("}\n") and "NaN" not in text
    assert json.loads(text) == {"value": None, "scale": 2.0}


# --------------------------------------------------------------------------- library writers

def test_library_writers_refuse_a_directory_and_leave_no_temporary(tmp_path):
    from knockgs_core.reporting import write_table

    folder = tmp_path / "main.csv"
    folder.mkdir()
    df = pd.DataFrame({"method": ["a"], "x": [1.0]})
    with pytest.raises(InputError, match="directory"):
        write_table(df, folder)
    with pytest.raises(InputError, match="directory"):
        write_json(folder, {"a": 1})
    write_table(df, tmp_path / "t.csv", tmp_path / "t.md", title="T")
    assert (tmp_path / "t.csv").read_text() == "method,x\na,1\n"
    assert (tmp_path / "t.md").read_text().startswith("# T\n")
    assert _temp_files(tmp_path) == []


def test_ply_and_particle_writers_are_atomic(tmp_path, monkeypatch):
    from knockgs_core.assets import GaussianSet, ParticleSet, load_particles, read_ply, save_particles, write_ply

    rng = np.random.default_rng(0)
    n = 5
    gs = GaussianSet(rng.normal(size=(n, 3)), np.full((n, 3), 0.1), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.full(n, 0.5), rng.uniform(size=(n, 3)), np.zeros((n, 0, 3)))
    ps = ParticleSet(positions=np.full((n, 3), 1.0), volumes=None, n_gs=n, gaussian_index=np.arange(n), region=np.zeros(n))
    write_ply(gs, tmp_path / "g.ply")
    save_particles(ps, tmp_path / "p.npz")
    ply_before, npz_before = (tmp_path / "g.ply").read_bytes(), (tmp_path / "p.npz").read_bytes()
    np.testing.assert_allclose(read_ply(tmp_path / "g.ply").means, gs.means, rtol=1e-6)
    assert load_particles(tmp_path / "p.npz").n_gs == n

    monkeypatch.setattr(_io.os, "replace", lambda src, dst: (_ for _ in ()).throw(OSError("no space left")))
    moved = GaussianSet(gs.means + 1.0, gs.scales, gs.quats, gs.opacities, gs.sh_dc, gs.sh_rest)
    with pytest.raises(OSError):
        write_ply(moved, tmp_path / "g.ply")
    with pytest.raises(OSError):
        save_particles(ParticleSet(positions=np.full((n, 3), 1.5), volumes=None, n_gs=n, gaussian_index=np.arange(n),
                                   region=np.zeros(n)), tmp_path / "p.npz")
    assert (tmp_path / "g.ply").read_bytes() == ply_before and (tmp_path / "p.npz").read_bytes() == npz_before
    assert _temp_files(tmp_path) == []


@pytest.mark.parametrize("error", [RuntimeError("render failed"), KeyboardInterrupt()])
def test_a_failed_or_interrupted_job_leaves_no_output_folder(tmp_path, error):
    import io

    from knockgs_core.io import staged_folders

    folder, F_folder = tmp_path / "eval" / "theta", tmp_path / "evalF" / "theta"
    log = io.StringIO()
    with pytest.raises(type(error)):
        with staged_folders(folder, F_folder, log=log) as (stage, F_stage):
            (stage / "standard_x.parquet").write_bytes(b"written")  # the first probe's file, then the failure
            (F_stage / "standard_x.F.parquet").write_bytes(b"written")
            raise error
    assert not folder.exists() and not F_folder.exists()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["eval", "evalF"]  # no staging folder either
    assert log.getvalue().splitlines() == [f"removed the partial output {stage}", f"removed the partial output {F_stage}"]


def test_output_folders_appear_only_when_the_job_ends(tmp_path):
    from knockgs_core.io import staged_folders, staging_folder

    folder, F_folder = tmp_path / "lib" / "chunk0", tmp_path / "libF" / "chunk0"
    with staged_folders(folder, F_folder, folder) as stages:
        assert stages == [tmp_path / "lib" / ".chunk0.partial", tmp_path / "libF" / ".chunk0.partial",
                          tmp_path / "lib" / ".chunk0.partial"]  # a folder named twice is built once
        assert stages[0] == staging_folder(folder) and stages[0].is_dir() and list(stages[0].iterdir()) == []
        (stages[0] / "a.parquet").write_bytes(b"a")
        (stages[1] / "a.F.parquet").write_bytes(b"F")
        assert not folder.exists() and not F_folder.exists()  # nothing in place while the job runs
    assert (folder / "a.parquet").read_bytes() == b"a" and (F_folder / "a.F.parquet").read_bytes() == b"F"
    assert not stages[0].exists() and not stages[1].exists()
    # a job run again (its rule forced) replaces its older folder whole: no file of the old one is kept
    (folder / "stale.parquet").write_bytes(b"old")
    with staged_folders(folder) as (stage,):
        (stage / "b.parquet").write_bytes(b"b")
        assert (folder / "stale.parquet").exists()  # the old output stays until the new one is whole
    assert sorted(p.name for p in folder.iterdir()) == ["b.parquet"]
    # an output path that is a file is refused, naming it, before anything is written
    (tmp_path / "taken").write_text("a file")
    with pytest.raises(InputError, match="taken.*exists and is not a folder"):
        with staged_folders(tmp_path / "taken"):
            pass
    assert (tmp_path / "taken").read_text() == "a file" and not (tmp_path / ".taken.partial").exists()


def test_a_jobs_files_map_into_the_staging_folders_of_their_folders(tmp_path):
    from knockgs_core.io import StagedFolders, check_files_in, staged_folders

    folder, F_folder = tmp_path / "eval" / "theta", tmp_path / "evalF" / "theta"
    with staged_folders(folder, F_folder) as stages:
        assert stages.path(folder / "standard_x.parquet") == tmp_path / "eval" / ".theta.partial" / "standard_x.parquet"
        assert stages.path(str(F_folder / "standard_x.F.parquet")) == stages[1] / "standard_x.F.parquet"
        assert stages.path(None) is None
        # a file outside the folders, or in a subfolder of one, is refused by name: a job writes its folders' files
        for outside in (tmp_path / "eval" / "other" / "a.parquet", folder / "deeper" / "a.parquet"):
            with pytest.raises(InputError) as exc:
                stages.path(outside)
            assert exc.value.field == "output" and str(outside) in str(exc.value) and "\n" not in str(exc.value)
    # the same check, up front, for all of a job's files; written in place, files map to themselves
    check_files_in([folder / "a.parquet", None, F_folder / "a.F.parquet"], [folder, F_folder], source="rollout job")
    with pytest.raises(InputError, match=r"^rollout job: field 'output': .*b\.parquet lies outside"):
        check_files_in([folder / "a.parquet", tmp_path / "b.parquet"], [folder], source="rollout job")
    in_place = StagedFolders([folder, F_folder], [folder, F_folder])
    assert in_place == [folder, F_folder] and in_place.path(folder / "a.parquet") == folder / "a.parquet"


_KILLED_JOB = """
import os, signal, sys
from pathlib import Path
from knockgs_core.io import staged_folders
folder = Path(sys.argv[1])
with staged_folders(folder) as (stage,):
    (stage / "standard_x.parquet").write_bytes(b"written")
    os.kill(os.getpid(), getattr(signal, sys.argv[2]))  # no handler: Python runs no clean-up
    (stage / "standard_y.parquet").write_bytes(b"written")
"""


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGKILL"])
def test_a_killed_job_leaves_no_output_folder_and_its_rerun_clears_the_staging(tmp_path, sig):
    import io
    import subprocess
    import sys

    from knockgs_core.io import staged_folders

    folder = tmp_path / "frames" / "theta"
    out = subprocess.run([sys.executable, "-c", _KILLED_JOB, str(folder), sig], capture_output=True, text=True)
    assert out.returncode == -getattr(__import__("signal"), sig), out.stderr
    assert not folder.exists()  # what a workflow manager checks: the output is missing, so the job runs again
    stage = tmp_path / "frames" / ".theta.partial"
    assert sorted(p.name for p in stage.iterdir()) == ["standard_x.parquet"]  # the killed attempt's half
    log = io.StringIO()
    with staged_folders(folder, log=log) as (new_stage,):
        assert new_stage == stage and list(stage.iterdir()) == []  # the rerun starts from an empty folder
        for name in ("standard_x.parquet", "standard_y.parquet"):
            (stage / name).write_bytes(b"rerun")
    assert log.getvalue().splitlines() == [f"removed the partial output {stage}"]
    assert sorted(p.name for p in folder.iterdir()) == ["standard_x.parquet", "standard_y.parquet"]
    assert not stage.exists()


def _frames(t=6, n=700, c=3, seed=0):
    return np.random.default_rng(seed).random((t, n, c), dtype=np.float32)


def _streamed(path, values, columns, meta=b'{"a": 1}', **kw):
    from knockgs_core.io import LongFormatStream

    stream = LongFormatStream(path, columns, **kw)
    for t, frame in enumerate(values):
        stream.put(t, frame)
    stream.finish({b"knockgs": meta}, n_frames=len(values))
    stream.wait()


@pytest.mark.parametrize("group_rows", [1, 1500, 10**9])
def test_a_long_file_written_frame_by_frame_decodes_as_the_whole_table(tmp_path, group_rows, monkeypatch):
    # row groups of one frame, of three frames (the last group shorter) and a single one; and
    # without pyarrow's add_key_value_metadata (older pyarrow): the file written whole at the end
    import pyarrow.parquet as pq

    import knockgs_core.io._long_writer as _long_writer
    from knockgs_core.io import read_long_values, read_metadata
    from knockgs_core.io import LONG_COMPRESSION, long_encoding, long_table

    X = _frames(t=7)
    whole = long_table(X, ["x", "y", "z"]).replace_schema_metadata({b"knockgs": b'{"a": 1}'})
    write_parquet(tmp_path / "whole.parquet", whole, compression=LONG_COMPRESSION,
                  column_encoding=long_encoding(whole.column_names))
    for can_stream in (True, False):
        monkeypatch.setattr(_long_writer, "CAN_STREAM", can_stream)
        path = tmp_path / f"s{can_stream}.parquet"
        _streamed(path, X, ["x", "y", "z"], group_rows=group_rows)
        assert pq.read_table(path).equals(pq.read_table(tmp_path / "whole.parquet"))  # rows in the writers' order
        assert pq.read_schema(path).equals(pq.read_schema(tmp_path / "whole.parquet"), check_metadata=True)
        assert read_metadata(path, b"knockgs") == {"a": 1}
        assert read_long_values(path, ["x", "y", "z"]).tobytes() == X.tobytes()
        groups = pq.ParquetFile(path).metadata.num_row_groups
        assert groups == ({1: 7, 1500: 3, 10**9: 1}[group_rows] if can_stream else 1)
    assert _temp_files(tmp_path) == []


def test_a_frame_by_frame_writer_refuses_a_dropped_or_repeated_frame_and_leaves_nothing(tmp_path):
    from knockgs_core.io import LongFormatStream

    X = _frames()
    for bad in ([0, 1, 1], [0, 2], [1]):
        stream = LongFormatStream(tmp_path / "r.parquet", ["x", "y", "z"], group_rows=1)
        with pytest.raises(InputError, match=r"r\.parquet.*frame .* was due"):
            for t in bad:
                stream.put(t, X[t])
        stream.abort()
        assert list(tmp_path.iterdir()) == []
    # as many frames as the metadata lists, or the stream is aborted and raises
    stream = LongFormatStream(tmp_path / "r.parquet", ["x", "y", "z"], group_rows=1)
    for t in range(3):
        stream.put(t, X[t])
    with pytest.raises(InputError, match="3 frames handed over, expected 6"):
        stream.finish({b"knockgs": b"{}"}, n_frames=6)
    # another particle count, or another number of columns, is refused too
    stream = LongFormatStream(tmp_path / "r.parquet", ["x", "y", "z"])
    stream.put(0, X[0])
    with pytest.raises(InputError, match="particle.*shape"):
        stream.put(1, X[1, :-1])
    with pytest.raises(InputError, match="particle.*shape"):
        stream.put(1, X[1, :, :2])
    stream.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="group_rows"):
        LongFormatStream(tmp_path / "r.parquet", ["x"], group_rows=0)
    (tmp_path / "dir.parquet").mkdir()
    with pytest.raises(InputError, match="dir.parquet.*directory"):
        LongFormatStream(tmp_path / "dir.parquet", ["x"])


@pytest.mark.parametrize("failure", ["abort", "non-finite", "rename"])
def test_a_frame_by_frame_writer_that_fails_midway_leaves_no_file_and_no_temporary(tmp_path, failure, monkeypatch):
    import time

    from knockgs_core.io import LongFormatStream

    X = _frames(t=8)
    if failure == "non-finite":
        X[5, 3, 1] = np.inf
    if failure == "rename":
        monkeypatch.setattr(_io.os, "replace", lambda src, dst: (_ for _ in ()).throw(OSError("read-only file system")))
    target = tmp_path / "r.parquet"
    stream = LongFormatStream(target, ["x", "y", "z"], group_rows=1, refuse_non_finite="positions")
    for t in range(4):
        stream.put(t, X[t])
    deadline = time.monotonic() + 10
    while not _temp_files(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert _temp_files(tmp_path) != [] and not target.exists()  # midway: row groups in the temporary file
    if failure == "abort":
        stream.abort()
    else:  # the failure is raised by a later put, by finish or by wait, whichever comes after it
        with pytest.raises((InputError, OSError), match="non-finite positions|read-only"):
            for t in range(4, 8):
                stream.put(t, X[t])
            stream.finish({b"knockgs": b"{}"}, n_frames=8)
            stream.wait()
    assert list(tmp_path.iterdir()) == []


def test_a_program_that_ends_before_finishing_a_stream_leaves_nothing_and_exits(tmp_path):
    # the writer thread notices that the main thread has ended: no hang, no temporary file
    import subprocess
    import sys

    code = ("import numpy as np; from knockgs_core.io import LongFormatStream as S; "
            f"s = S({str(tmp_path / 'r.parquet')!r}, ['x'], group_rows=1); s.put(0, np.zeros((5, 1), np.float32)); "
            "raise KeyboardInterrupt")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=60)
    assert done.returncode != 0 and b"KeyboardInterrupt" in done.stderr
    assert list(tmp_path.iterdir()) == []
