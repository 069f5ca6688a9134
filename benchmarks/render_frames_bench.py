"""``render_frames`` against rendering each frame's deformed scene (``render(*deformed_scene(...))``):
a random scene of N Gaussians (55 % static) moved over 4 frames at 160x120, medians of 3 runs.

    python3 benchmarks/render_frames_bench.py --gaussians 200000 [--device cuda:0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()

    from knockgs_core.render import Camera, deformed_scene, render, render_frames

    rng = np.random.default_rng(0)
    n, T = args.gaussians, args.frames
    means = rng.uniform(0.7, 1.3, (n, 3))
    A = rng.normal(size=(n, 3, 3)) * 0.004
    cov = A @ A.transpose(0, 2, 1)
    colors, opac = rng.uniform(size=(n, 3)), rng.uniform(0.3, 1.0, n)
    static = rng.uniform(size=n) < 0.55
    m = int((~static).sum())
    pos = (means[~static][None] + 0.01 * rng.normal(size=(T, m, 3))).astype(np.float32)
    F = (np.eye(3) + 0.05 * rng.normal(size=(T, m, 3, 3))).astype(np.float32)
    w2c = np.eye(4)
    w2c[:3, 3] = [-1.0, -1.0, 2.6]
    cam = Camera(width=160, height=120, fx=160, fy=160, cx=80, cy=60, world_to_camera=w2c)
    render_frames(means, cov, colors, opac, static, pos[:1], F[:1], cam, device=args.device)  # kernels loaded

    per_frame, once = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        a = [render(*deformed_scene(means, cov, colors, opac, pos[t], F[t], static), cam, device=args.device)
             for t in range(T)]
        per_frame.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        b = render_frames(means, cov, colors, opac, static, pos, F, cam, device=args.device)
        once.append(time.perf_counter() - t0)
    same = all(np.array_equal(x.rgb, y.rgb) and np.array_equal(x.alpha, y.alpha) for x, y in zip(a, b))
    t_old, t_new = float(np.median(per_frame)) / T, float(np.median(once)) / T
    print(f"{n:,} Gaussians on {args.device}: per frame render(*deformed_scene) {t_old:.3f} s, render_frames "
          f"{t_new:.3f} s a frame ({t_old / t_new:.2f}x); frames identical: {same}")


if __name__ == "__main__":
    main()
