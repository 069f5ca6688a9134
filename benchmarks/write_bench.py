"""Writing and reading one rollout file at paper scale: the long-format encoding in use
(:func:`knockgs_core.rollout.write_rollout`) against the earlier one (zstd, dictionaries).

The rollout is synthetic but of the paper-scale Pillow's size and kind: 695,881 particles in
random order (a particle's index says nothing of its place, as in an asset), 31 frames of a
smooth displacement of a few centimetres. Both writers build the Arrow table from the
(T, N, 3) float32 positions and write through the same atomic writer; the reads go through
:func:`knockgs_core.rollout.read_rollout`, and the positions read back must equal the ones
written, bit for bit.

    python3 benchmarks/write_bench.py [--particles 695881] [--frames 31] [--repeats 5]

``--stream``: the whole-file write after the rollout (:func:`write_rollout`, and
:func:`write_deformation` with ``--F``) against the files written frame by frame while it
runs (:class:`knockgs_core.rollout.RolloutStream`). The frames are handed over one every
``--interval`` seconds (the host waiting for the GPU's next frame; 0: all at once, the
writer's own pace); the tail is the time from the last frame handed over to the files
closed, the total from the first frame handed over. With ``--F`` the first 83.7 % of the
particles (the paper Pillow's Gaussian-associated share) also get deformation gradients.
The files read back must equal the whole-file ones bit for bit.

    python3 benchmarks/write_bench.py --stream --frames 61 [--interval 0.1] [--F] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

from knockgs_core.io import write_parquet
from knockgs_core.rollout import (Rollout, RolloutStream, read_deformation, read_rollout, write_deformation,
                                  write_rollout)


def synthetic_rollout(n: int, t: int, *, seed: int = 0, n_F: int = 0) -> Rollout:
    """Positions (t, n, 3) float32 [m] of a smooth motion of random rest positions, and with
    ``n_F`` deformation gradients (t, n_F, 3, 3) near the identity."""
    rng = np.random.default_rng(seed)
    rest = rng.random((n, 3), dtype=np.float32) * np.float32(0.8) + np.float32(0.6)
    times = np.linspace(0.0, 0.6, t)
    amp = 0.02 * np.sin(2 * np.pi * times / 0.3)[:, None, None]
    X = (rest[None] + amp * np.sin(3.0 * rest[None])).astype(np.float32)
    F = None
    if n_F:
        strain = (amp[:, :, :, None] * np.cos(3.0 * rest[None, :n_F, :, None])).astype(np.float32)
        F = np.broadcast_to(np.eye(3, dtype=np.float32), (t, n_F, 3, 3)) + strain * np.float32(3.0)
    meta = {"object": "pillow", "profile": "paper", "theta": [1.0, 1.0], "probe": "standard_y", "n_gs": n_F or n,
            "n_fill": n - (n_F or n), "export_times": times.tolist()}
    return Rollout(positions=X, F=F, meta=meta)


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


def write_whole(folder: Path, rollout: Rollout) -> float:
    """Seconds to write the finished rollout's files whole."""
    t0 = time.perf_counter()
    write_rollout(folder / "whole.parquet", rollout)
    if rollout.F is not None:
        write_deformation(folder / "whole.F.parquet", rollout)
    return time.perf_counter() - t0


def write_streamed(folder: Path, rollout: Rollout, interval: float) -> tuple[float, float]:
    """(tail, total) seconds of the files written frame by frame, a frame every ``interval`` s."""
    F_path = None if rollout.F is None else folder / "stream.F.parquet"
    stream = RolloutStream(folder / "stream.parquet", F_path)
    t0 = time.perf_counter()
    for t in range(len(rollout.positions)):
        if t:
            time.sleep(interval)  # the next frame being simulated (the host waits for the GPU)
        stream.frame(t, rollout.positions[t], None if rollout.F is None else rollout.F[t])
    t_last = time.perf_counter()
    stream.finish(rollout.meta)
    stream.wait()
    end = time.perf_counter()
    return end - t_last, end - t0


def same_files(folder: Path, rollout: Rollout) -> bool:
    """The streamed files decode to the whole ones, bit for bit (positions, F, metadata)."""
    a, b = read_rollout(folder / "whole.parquet"), read_rollout(folder / "stream.parquet")
    same = a.positions.tobytes() == b.positions.tobytes() == rollout.positions.tobytes() and a.meta == b.meta
    if rollout.F is not None:
        same = same and read_deformation(folder / "whole.F.parquet").tobytes() == \
            read_deformation(folder / "stream.F.parquet").tobytes()
    return same


def main_stream(args) -> None:
    n_F = int(round(args.particles * 582_385 / 695_881)) if args.F else 0
    ro = synthetic_rollout(args.particles, args.frames, n_F=n_F)
    whole, tail, total = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):  # interleaved, median of each; new files each time, as in a job
            folder = Path(tmp) / str(k)
            folder.mkdir()
            whole.append(write_whole(folder, ro))
            a, b = write_streamed(folder, ro, args.interval)
            tail.append(a)
            total.append(b)
            assert same_files(folder, ro)
            shutil.rmtree(folder)
    frames = (args.frames - 1) * args.interval
    print(f"{args.particles:,} particles x {args.frames} frames{f', F of {n_F:,}' if n_F else ''}, a frame every "
          f"{args.interval:g} s, median of {args.repeats}; streamed files == whole files bit for bit on decode")
    print("| write | s after the last frame | s in all (frames handed over in {:.2f} s) |".format(frames))
    print("|---|---:|---:|")
    print(f"| whole files, after the rollout | {statistics.median(whole):.3f} | {statistics.median(whole):.3f} |")
    print(f"| frame by frame, while it runs | {statistics.median(tail):.3f} | {statistics.median(total):.3f} |")
    print(f"tail {statistics.median(tail) / statistics.median(whole):.3f}x the whole write "
          f"(all tails: {', '.join(f'{x:.3f}' for x in tail)})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=695_881)
    ap.add_argument("--frames", type=int, default=31)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stream", action="store_true", help="whole-file write against frame-by-frame")
    ap.add_argument("--interval", type=float, default=0.1, help="--stream: seconds between frames handed over")
    ap.add_argument("--F", action="store_true", help="--stream: deformation gradients too")
    args = ap.parse_args()
    if args.stream:
        return main_stream(args)
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
