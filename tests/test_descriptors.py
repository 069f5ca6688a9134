"""Descriptor (SPEC §5): analytic answers, a float64 reference, input errors, Parquet reading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from knockgs_core.descriptors import (
    FEATURE_NAMES,
    descriptor,
    descriptor_from_rollout,
    descriptor_table,
    read_positions,
    rms_curves,
)
from knockgs_core.errors import InputError

FICUS = Path(__file__).parent / "data" / "knockgs-ficus"


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


def translating_pair(n_frames=31):
    """Two particles at distance 1 (along x), both moving +1 along y per frame."""
    t = np.arange(n_frames, dtype=np.float32)
    x = np.zeros((n_frames, 2, 3), dtype=np.float32)
    x[:, 1, 0] = 1.0
    x[:, :, 1] = t[:, None]
    return x


def random_rollout(rng, n_frames=31, n_particles=40):
    x0 = rng.uniform(0.5, 1.5, size=(n_particles, 3))
    steps = rng.normal(scale=2e-3, size=(n_frames - 1, n_particles, 3))
    x = np.concatenate([x0[None], x0[None] + np.cumsum(steps, axis=0)])
    return x.astype(np.float32)


def reference_descriptor(x):
    """Obviously-correct float64 transcription of SPEC §5."""
    x = np.asarray(x, dtype=np.float64)
    d = np.linalg.norm(x[0].max(axis=0) - x[0].min(axis=0))
    r = np.array([np.sqrt(np.mean(np.sum((x[t] - x[0]) ** 2, axis=1))) / d for t in range(len(x))])
    v = np.array(
        [0.0]
        + [np.sqrt(np.mean(np.sum((x[t] - x[t - 1]) ** 2, axis=1))) / d for t in range(1, len(x))]
    )
    return np.array([r.sum(), (r[5] - r[0]) / 5, v.max(), v.sum(), v[1:6].sum() / v.sum()])


def test_feature_names_match_the_authors_tables():
    header = pd.read_csv(FICUS / "library.csv", nrows=0).columns
    assert tuple(header[3:]) == FEATURE_NAMES


def test_translating_pair_analytic():
    # D = 1 (bbox diagonal of two points at distance 1); r^t = t, v^t = 1 (t >= 1):
    # phi = (sum_{t=0}^{30} t, (5 - 0)/5, 1, 30, 5/30)
    phi = descriptor(translating_pair())
    np.testing.assert_allclose(phi, [465.0, 1.0, 1.0, 30.0, 1.0 / 6.0], rtol=1e-6)
    assert phi.shape == (5,) and phi.dtype == np.float64


def test_accelerating_pair_analytic():
    # displacement t^2 / 100 along z with D = 1: r^t = t^2/100, v^t = (2t - 1)/100
    t = np.arange(31, dtype=np.float32)
    x = translating_pair()
    x[:, :, 1] = 0.0
    x[:, :, 2] = (t**2 / 100.0)[:, None]
    phi = descriptor(x)
    expected = [9455 / 100, 25 / 500, 59 / 100, 900 / 100, 25 / 900]
    np.testing.assert_allclose(phi, expected, rtol=2e-6)


def test_curves_start_at_zero_and_match_float64_reference(rng):
    x = random_rollout(rng)
    r, v = rms_curves(x)
    assert r.dtype == np.float32 and v.dtype == np.float32
    assert r[0] == 0 and v[0] == 0
    np.testing.assert_allclose(descriptor(x), reference_descriptor(x), rtol=2e-5)


def test_float32_arithmetic_for_float64_input(rng):
    x = random_rollout(rng).astype(np.float64) + rng.normal(scale=1e-9, size=(31, 40, 3))
    assert np.array_equal(descriptor(x), descriptor(x.astype(np.float32)))


def test_invariant_to_scale_and_offset(rng):
    x = random_rollout(rng)
    phi = descriptor(x)
    np.testing.assert_allclose(descriptor(x * np.float32(4.0)), phi, rtol=1e-6)
    np.testing.assert_allclose(descriptor(x + np.float32(0.25)), phi, rtol=1e-4)


def test_particle_order_does_not_matter(rng):
    x = random_rollout(rng)
    shuffled = x[:, rng.permutation(x.shape[1])]
    np.testing.assert_allclose(descriptor(shuffled), descriptor(x), rtol=1e-6)


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda x: x[:30], "frame"),  # 30 frames, 31 required
        (lambda x: x[..., :2], "positions"),  # not [T, N, 3]
        (lambda x: x[:, 0], "positions"),  # 2-D
        (lambda x: x[:, :0], "particle"),  # no particles
        (lambda x: np.where(np.arange(31)[:, None, None] == 7, np.nan, x), "positions"),
        (lambda x: np.where(np.arange(31)[:, None, None] == 3, np.inf, x), "positions"),
        (lambda x: np.repeat(x[:, :1], 2, axis=1), "positions"),  # coincident: D = 0
        (lambda x: x[:, :1], "positions"),  # one particle: D = 0
        (lambda x: np.repeat(x[:1], 31, axis=0), "positions"),  # no motion
    ],
)
def test_bad_positions_raise_input_error(make, field):
    with pytest.raises(InputError) as err:
        descriptor(make(translating_pair()), source="case_x")
    assert err.value.field == field
    assert err.value.source == "case_x"


def test_frame_count_check_is_optional():
    x = translating_pair(20)
    with pytest.raises(InputError, match="expected 31 frames"):
        descriptor(x)
    assert descriptor(x, n_frames=None)[0] == pytest.approx(190.0)
    with pytest.raises(InputError, match="at least 6 frames"):
        descriptor(translating_pair(5), n_frames=None)


def write_rollout(path, x, *, shuffle_rng=None, drop=None, dtype=np.float32):
    n_t, n_p, _ = x.shape
    frame = np.repeat(np.arange(n_t, dtype=np.int32), n_p)
    particle = np.tile(np.arange(n_p, dtype=np.int32) * 3 + 1, n_t)  # ids need not be 0..N-1
    xyz = x.reshape(-1, 3).astype(dtype)
    keep = np.ones(frame.size, bool)
    if drop is not None:
        keep[drop] = False
    order = np.flatnonzero(keep)
    if shuffle_rng is not None:
        order = shuffle_rng.permutation(order)
    table = pa.table(
        {
            "frame": frame[order],
            "particle": particle[order],
            "x": xyz[order, 0],
            "y": xyz[order, 1],
            "z": xyz[order, 2],
        }
    )
    pq.write_table(table, path)
    return path


def test_rollout_round_trip_sorts_rows(tmp_path, rng):
    x = random_rollout(rng)
    path = write_rollout(tmp_path / "r.parquet", x, shuffle_rng=rng)
    assert np.array_equal(read_positions(path), x)
    assert np.array_equal(descriptor_from_rollout(path), descriptor(x))


def test_rollout_particle_subset(tmp_path, rng):
    x = random_rollout(rng)
    path = write_rollout(tmp_path / "r.parquet", x)
    ids = [1, 7, 31, 118]  # ids are 3 * index + 1
    np.testing.assert_array_equal(
        descriptor_from_rollout(path, particles=ids), descriptor(x[:, [0, 2, 10, 39]])
    )
    with pytest.raises(InputError) as err:
        descriptor_from_rollout(path, particles=[1, 2])
    assert err.value.field == "particle" and str(path) in str(err.value)


@pytest.mark.parametrize(
    "drop, field",
    [
        ([40 * 12 + 5], "particle"),  # one particle missing in frame 12
        (list(range(40 * 30, 40 * 31)), None),  # last frame missing: 30 frames, 31 expected
        (list(range(40 * 4, 40 * 5)), "frame"),  # frame 4 missing: a gap
    ],
)
def test_rollout_missing_rows(tmp_path, rng, drop, field):
    path = write_rollout(tmp_path / "r.parquet", random_rollout(rng), drop=drop)
    with pytest.raises(InputError) as err:
        descriptor_from_rollout(path)
    assert err.value.source == str(path)
    assert err.value.field == (field or "frame")


def test_rollout_duplicate_row_and_missing_column(tmp_path, rng):
    x = random_rollout(rng, n_particles=3)
    path = write_rollout(tmp_path / "r.parquet", x)
    table = pq.read_table(path)
    # frame 2 gets particle 4 twice and loses particle 7: same row count, not the same set
    particle = table.column("particle").to_numpy().copy()
    particle[2 * 3 + 2] = 4
    pq.write_table(table.set_column(1, "particle", pa.array(particle)), tmp_path / "dup.parquet")
    with pytest.raises(InputError, match="duplicate row for frame 2"):
        read_positions(tmp_path / "dup.parquet")
    pq.write_table(table.drop(["z"]), tmp_path / "noz.parquet")
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "noz.parquet")
    assert err.value.field == "z"
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "absent.parquet")
    assert err.value.field == "file"


def test_rows_in_the_writers_order_read_as_shuffled_rows(tmp_path, rng):
    # ids 0..N-1, frame-major: the layout the writers use, read without a sort; the same
    # array, bit for bit, as the same rows shuffled (the sorting path), in float64 too
    x = random_rollout(rng)
    n_t, n_p, _ = x.shape
    frame = np.repeat(np.arange(n_t, dtype=np.int32), n_p)
    particle = np.tile(np.arange(n_p, dtype=np.int32), n_t)
    xyz = x.reshape(-1, 3).astype(np.float64) * (1 + 1e-9)  # float64 values round to float32 on read
    perm = rng.permutation(frame.size)
    for name, order in (("canonical", np.arange(frame.size)), ("shuffled", perm)):
        pq.write_table(pa.table({"frame": frame[order], "particle": particle[order], "x": xyz[order, 0],
                                 "y": xyz[order, 1], "z": xyz[order, 2]}), tmp_path / f"{name}.parquet")
    a, b = read_positions(tmp_path / "canonical.parquet"), read_positions(tmp_path / "shuffled.parquet")
    assert a.dtype == np.float32 and a.shape == x.shape
    assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
    assert np.array_equal(a, xyz.reshape(n_t, n_p, 3).astype(np.float32))
    ids = [0, 5, n_p - 1]
    assert np.array_equal(read_positions(tmp_path / "canonical.parquet", particles=ids), a[:, ids])
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "canonical.parquet", particles=[n_p])
    assert err.value.field == "particle"
    # a non-finite value is named by its column; frames 1..T are not 0..T-1
    bad = xyz.copy()
    bad[7, 1] = np.nan
    pq.write_table(pa.table({"frame": frame, "particle": particle, "x": bad[:, 0], "y": bad[:, 1], "z": bad[:, 2]}),
                   tmp_path / "nan.parquet")
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "nan.parquet")
    assert err.value.field == "y"
    pq.write_table(pa.table({"frame": frame + 1, "particle": particle, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}),
                   tmp_path / "late.parquet")
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "late.parquet")
    assert err.value.field == "frame"


def test_canonical_files_are_read_row_group_by_row_group_and_others_as_before(tmp_path, rng, monkeypatch):
    # a file in the writers' order is read a row group at a time into the result (row groups
    # of 7 rows cut frames anywhere), never as one whole table; a file with no statistics, a
    # row group out of order or a null takes the general path: the same array, or its error
    x = random_rollout(rng)
    n_t, n_p, _ = x.shape
    frame = np.repeat(np.arange(n_t, dtype=np.int32), n_p)
    particle = np.tile(np.arange(n_p, dtype=np.int32), n_t)
    xyz = x.reshape(-1, 3)

    def write(name, order=slice(None), **options):
        cols = {"frame": frame[order], "particle": particle[order], "x": xyz[order, 0], "y": xyz[order, 1],
                "z": xyz[order, 2]}
        pq.write_table(pa.table(cols), tmp_path / name, row_group_size=7, **options)
        return tmp_path / name

    swap = np.arange(frame.size)
    swap[[3, 4]] = swap[[4, 3]]  # one pair of rows out of order, inside a row group
    files = {"canonical": write("canonical.parquet"), "no_stats": write("no_stats.parquet", write_statistics=False),
             "swapped": write("swapped.parquet", swap)}
    assert pq.ParquetFile(files["canonical"]).metadata.num_row_groups == -(-frame.size // 7)
    general = pq.read_table
    whole_reads = []
    monkeypatch.setattr(pq, "read_table", lambda *a, **k: whole_reads.append(a[0]) or general(*a, **k))
    for name, path in files.items():
        whole_reads.clear()
        got = read_positions(path)
        assert got.dtype == np.float32 and np.array_equal(got, x), name
        assert whole_reads == ([] if name == "canonical" else [str(path)]), name
    nulls = pa.table({"frame": frame, "particle": particle, "x": pa.array(xyz[:, 0], mask=np.arange(frame.size) == 9),
                      "y": xyz[:, 1], "z": xyz[:, 2]})
    pq.write_table(nulls, tmp_path / "null.parquet", row_group_size=7)
    with pytest.raises(InputError, match="1 null values") as err:
        read_positions(tmp_path / "null.parquet")
    assert err.value.field == "x"
    short = pa.table({"frame": frame[:-1], "particle": particle[:-1], "x": xyz[:-1, 0], "y": xyz[:-1, 1],
                      "z": xyz[:-1, 2]})
    pq.write_table(short, tmp_path / "short.parquet", row_group_size=7)  # the last frame lacks a particle
    with pytest.raises(InputError) as err:
        read_positions(tmp_path / "short.parquet")
    assert err.value.field == "particle"


def test_descriptor_table(tmp_path, rng):
    a, b = random_rollout(rng), translating_pair()
    path = write_rollout(tmp_path / "a.parquet", a)
    table = descriptor_table({"case_a": path, "case_b": b})
    assert list(table.columns) == ["case_name", *FEATURE_NAMES]
    assert table["case_name"].tolist() == ["case_a", "case_b"]
    np.testing.assert_array_equal(table.iloc[0, 1:].to_numpy(float), descriptor(a))
    np.testing.assert_array_equal(table.iloc[1, 1:].to_numpy(float), descriptor(b))
    with pytest.raises(InputError, match="duplicate"):
        descriptor_table([("c", b), ("c", b)])


def test_library_and_query_tables_read_by_threads_are_the_serial_tables(tmp_path, rng):
    # rollout files read by several threads: the same rows in the candidates' order, and a bad
    # file named as the serial loop names it
    from knockgs_core.experiments import library_table, query_table
    from knockgs_core.rollout import Rollout, write_rollout

    names = [f"c{i}" for i in range(5)]
    paths = {}
    for name in names:
        x = random_rollout(rng)
        paths[name] = str(tmp_path / f"{name}.parquet")
        write_rollout(paths[name], Rollout(positions=x.astype(np.float32), F=None, meta={"theta": [1.0, 1.0]}))
    candidates = pd.DataFrame({"case_name": names[::-1], "E_scale": np.arange(5.0), "density_scale": np.ones(5)})
    serial = library_table(candidates, paths)
    threaded = library_table(candidates, paths, workers=3)
    assert list(serial.case_name) == names[::-1]
    pd.testing.assert_frame_equal(threaded, serial)
    assert serial[list(FEATURE_NAMES)].nunique().min() == 5  # the files differ, so would a mix-up
    pd.testing.assert_frame_equal(query_table(paths, workers=4), query_table(paths))
    bad = tmp_path / "bad.parquet"
    bad.write_text("not parquet")
    with pytest.raises(InputError, match="bad.parquet"):
        query_table({**paths, "bad": str(bad)}, workers=3)
