"""Renderer speed: seconds per frame of ``knockgs_core.render.render`` by scene size.

Scene: ``N`` anisotropic Gaussians (random rotations, axis scales log-uniform in
[0.005, 0.03]), centres uniform in the unit cube around (1, 1, 1) -- the object box
of the MPM domain -- opacities uniform in [0.3, 1]; camera 2.6 from the centre, 40
degree vertical field of view, so the object fills most of the frame. Each case runs
one warm-up render, then ``--repeats`` timed renders, and reports medians of the full
render and of its stages (project, bin_tiles on the host, rasterize).

A second table times ``bin_tiles + rasterize`` at each ``--tiles`` edge on the same
projection (the image is identical at every edge; only the work changes), as ratios to
the device's default edge (``TILE_SIZE_CPU`` = 4 on the CPU, ``TILE_SIZE`` = 16 on CUDA).

    python3 benchmarks/render_bench.py                      # CPU, 5k/50k x 256/512
    python3 benchmarks/render_bench.py --device cuda:0 --counts 50000 600000
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from knockgs_core._warp import warp_device
from knockgs_core.render import Camera, bin_tiles, project, rasterize, render
from knockgs_core.render._constants import tile_size_for


def scene(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    means = rng.uniform(0.5, 1.5, (n, 3))
    rot = Rotation.random(n, random_state=seed).as_matrix()
    s = np.exp(rng.uniform(np.log(0.005), np.log(0.03), (n, 3)))
    cov = np.einsum("nij,nj,nkj->nik", rot, s**2, rot)
    return means, cov, rng.uniform(0.0, 1.0, (n, 3)), rng.uniform(0.3, 1.0, n)


def timed(fn, repeats: int):
    out = fn()  # warm-up (and kernel load)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[5_000, 50_000])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="square image side [px]")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tiles", type=int, nargs="+", default=[2, 4, 8, 16], help="tile edges [px] compared in the second table")
    args = ap.parse_args()
    dev = warp_device(args.device)  # Warp started as the library starts it
    bin_device = None if dev.is_cpu else args.device  # as render() does

    print(f"device: {args.device} ({dev.name}); {platform.processor() or platform.machine()}; "
          f"warp {wp.__version__}; median of {args.repeats} repeats")
    print()
    print("| Gaussians | image | tile [px] | render [s/frame] | project [s] | bin_tiles [s] | rasterize [s] | tile pairs |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.counts:
        means, cov, colors, opac = scene(n)
        default_tile = tile_size_for(dev, n)  # the edge render() uses for this scene
        for size in args.sizes:
            cam = Camera.look_at([1.0, -1.6, 1.9], [1.0, 1.0, 1.0], [0.0, 0.0, 1.0],
                                 fov_deg=40.0, width=size, height=size)
            t_render, _ = timed(lambda: render(means, cov, colors, opac, cam, device=args.device), args.repeats)
            t_proj, proj = timed(lambda: project(means, cov, opac, cam, device=args.device), args.repeats)
            t_bin, bins = timed(lambda: bin_tiles(proj, size, size, tile_size=default_tile, device=bin_device), args.repeats)
            t_rast, _ = timed(lambda: rasterize(proj, colors, opac, bins, device=args.device), args.repeats)
            print(f"| {n:,} | {size}x{size} | {default_tile} | {t_render:.4f} | {t_proj:.4f} | {t_bin:.4f} | {t_rast:.4f} "
                  f"| {bins.gaussian_ids.size:,} |", flush=True)

    print()
    print("bin_tiles + rasterize by tile edge (ratio to the edge render() uses for the scene; lower is faster)")
    print()
    print("| Gaussians | image | render's edge | " + " | ".join(f"{t} px [s]" for t in args.tiles) + " | "
          + " | ".join(f"{t} px / render's" for t in args.tiles) + " |")
    print("|---:|---:|---:|" + "---:|" * (2 * len(args.tiles)))
    for n in args.counts:
        means, cov, colors, opac = scene(n)
        default_tile = tile_size_for(dev, n)
        for size in args.sizes:
            cam = Camera.look_at([1.0, -1.6, 1.9], [1.0, 1.0, 1.0], [0.0, 0.0, 1.0],
                                 fov_deg=40.0, width=size, height=size)
            proj = project(means, cov, opac, cam, device=args.device)
            t = {}
            for tile in args.tiles + [default_tile]:
                if tile not in t:
                    def run(tile=tile):
                        bins = bin_tiles(proj, size, size, tile_size=tile, device=bin_device)
                        return rasterize(proj, colors, opac, bins, device=args.device)

                    t[tile], _ = timed(run, args.repeats)
            print(f"| {n:,} | {size}x{size} | {default_tile} | " + " | ".join(f"{t[x]:.4f}" for x in args.tiles) + " | "
                  + " | ".join(f"{t[x] / t[default_tile]:.2f}" for x in args.tiles) + " |", flush=True)


if __name__ == "__main__":
    main()
