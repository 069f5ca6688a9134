"""Writing and reading one rollout file at paper scale: the long-format encoding in use
(:func:`knockgs_core.rollout.write_rollout`) against the earlier one (zstd, dictionaries).

The rollout is synthetic but of the paper-scale Pillow's size and kind: 695,881 particles in
random order (a particle's index says nothing of its place, as in an asset), 31 frames of a
smooth displacement of a few centimetres. Both writers build the Arrow table from the
(T, N, 3) float32 positions and write through the same atomic writer; the reads go through
:func:`knockgs_core.rollout.read_rollout`, and the positions read back must equal the ones
written, bit for bit.

    python3 benchmarks/write_bench.py [--particles 695881] [--frames 31] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

from knockgs_core._io import write_parquet
from knockgs_core.rollout import Rollout, read_rollout, write_rollout


def synthetic_rollout(n: int, t: int, *, seed: int = 0) -> Rollout:
    rng = np.random.default_rng(seed)
    rest = rng.random((n, 3), dtype=np.float32) * np.float32(0.8) + np.float32(0.6)
    times = np.linspace(0.0, 0.6, t)
    amp = 0.02 * np.sin(2 * np.pi * times / 0.3)[:, None, None]
    X = (rest[None] + amp * np.sin(3.0 * rest[None])).astype(np.float32)
    meta = {"object": "pillow", "profile": "paper", "theta": [1.0, 1.0], "probe": "standard_y", "n_gs": n, "n_fill": 0,
            "export_times": times.tolist()}
    return Rollout(positions=X, F=None, meta=meta)


def write_earlier(path, rollout: Rollout) -> None:
    """The earlier writer: zstd at its default level, dictionary-encoded columns."""
    X = rollout.positions
    T, N, _ = X.shape
    table = pa.table({"frame": pa.array(np.repeat(np.arange(T, dtype=np.int32), N)),
                      "particle": pa.array(np.tile(np.arange(N, dtype=np.int32), T)),
                      "x": pa.array(X[:, :, 0].reshape(-1)), "y": pa.array(X[:, :, 1].reshape(-1)),
                      "z": pa.array(X[:, :, 2].reshape(-1))})
    table = table.replace_schema_metadata({b"knockgs": json.dumps(rollout.meta).encode()})
    write_parquet(path, table, compression="zstd")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=695_881)
    ap.add_argument("--frames", type=int, default=31)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    ro = synthetic_rollout(args.particles, args.frames)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        writers = (("lz4 + delta/byte-split (in use)", write_rollout), ("zstd + dictionaries (earlier)", write_earlier))
        for name, writer in writers:
            path = Path(tmp) / f"{name.split()[0]}.parquet"
            w, r = [], []
            for _ in range(args.repeats):  # interleaved write and read, median of each
                t0 = time.perf_counter()
                writer(path, ro)
                w.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                back = read_rollout(path)
                r.append(time.perf_counter() - t0)
            assert np.array_equal(back.positions.view(np.uint32), ro.positions.view(np.uint32)), name
            rows.append((name, statistics.median(w), statistics.median(r), path.stat().st_size / 1e6))
    print(f"{args.particles:,} particles x {args.frames} frames, median of {args.repeats}")
    print("| encoding | write s | read s | MB |")
    print("|---|---:|---:|---:|")
    for name, w, r, mb in rows:
        print(f"| {name} | {w:.2f} | {r:.2f} | {mb:.0f} |")
    (_, w_new, r_new, mb_new), (_, w_old, r_old, mb_old) = rows
    print(f"write speed-up {w_old / w_new:.2f}x, read {r_old / r_new:.2f}x, size {mb_new / mb_old:.2f}x")


if __name__ == "__main__":
    main()
