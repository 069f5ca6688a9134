"""Per-frame time of ``render_frames``' two frame paths on one device, in one process:

- host-binned: each frame's projection read back to host NumPy arrays, binned (on the host on
  the CPU, by device sorts on CUDA, with the inputs uploaded again), the rasterizer's inputs
  uploaded, the image read back (``_pipeline._render_arrays``; the CPU default);
- device-resident: projection, visible compaction, depth and tile sorts and the rasterizer's
  inputs kept in Warp arrays allocated once per motion; only the pair count and the image come
  back (``_frame.DeviceFrames``; the CUDA default).

Scene: N Gaussians on a thin cushion-shaped shell (a superellipsoid of semi-axes 0.5 x 0.35 x
0.15 m around (1, 1, 1), like the paper's Pillow: ~584k Gaussians on its surface), flat
Gaussians tangent to the shell, all simulated; T frames of a small shear (positions and F),
rendered at W x H by a camera 1.45 m away. Times are seconds a frame: the median over
``--repeats`` renders of the whole motion (after a one-frame warm-up of each path, which loads
the kernels); the frames of the two paths are checked equal (rgb, depth, alpha).

    python3 benchmarks/render_frames_bench.py --device cuda:0
    python3 benchmarks/render_frames_bench.py --gaussians 200000 --frames 2 --repeats 3   # CPU
"""

from __future__ import annotations

import argparse
import time

import numpy as np

SEMI_AXES = np.array([0.5, 0.35, 0.15])
"""Semi-axes [m] of the shell (x, y, z)."""

CENTRE = np.array([1.0, 1.0, 1.0])
"""Centre of the shell [m]."""

SHELL_EXPONENT = 4.0
"""Superellipsoid exponent of the shell (2: an ellipsoid; 4: a cushion with rounded edges)."""


def shell_scene(n: int, rng) -> tuple:
    """``(means [n, 3], cov [n, 3, 3], colors [n, 3], opacities [n])`` of flat Gaussians on the
    shell: centres on the superellipsoid (radial jitter 1 mm), covariances ``s^2 (I - 0.96 d d^T)``
    with ``d`` the radial direction and ``s`` [m] about the spacing of the centres."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.sum(np.abs(d / SEMI_AXES) ** SHELL_EXPONENT, axis=1) ** (-1.0 / SHELL_EXPONENT)
    r += rng.normal(0.0, 1e-3, n)
    means = CENTRE + r[:, None] * d
    a, b, c = SEMI_AXES  # surface area, ellipsoid approximation (Thomsen), a little low for the cushion
    p = 1.6075
    area = 4.0 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)
    s = 1.5 * np.sqrt(area / n) * rng.uniform(0.7, 1.3, n)
    cov = s[:, None, None] ** 2 * (np.eye(3) - 0.96 * d[:, :, None] * d[:, None, :])
    colors = np.clip(0.5 + 0.8 * (means - CENTRE) / SEMI_AXES, 0.0, 1.0)
    return means, cov, colors, rng.uniform(0.5, 1.0, n)


def shear_motion(means: np.ndarray, frames: int, rng) -> tuple:
    """``(positions [T, n, 3], F [T, n, 3, 3])`` float32: a shear ``x += g(t) (z - z_c)`` with
    ``g`` up to 0.1, and F its gradient ``I + g(t) e_x e_z^T`` plus 1e-3 noise per Gaussian."""
    n = means.shape[0]
    pos = np.empty((frames, n, 3), np.float32)
    F = np.empty((frames, n, 3, 3), np.float32)
    for t in range(frames):
        g = 0.1 * np.sin(2.0 * np.pi * (t + 1) / max(frames, 4))
        pos[t] = means
        pos[t, :, 0] += g * (means[:, 2] - CENTRE[2])
        F[t] = np.eye(3) + 1e-3 * rng.normal(size=(n, 3, 3))
        F[t, :, 0, 2] += g
    return pos, F


def time_path(args: tuple, *, resident: bool, device: str, repeats: int) -> tuple[list[float], list]:
    """Seconds a frame of each of ``repeats`` renders of the motion ``args`` and the last frames."""
    from knockgs_core.render._deform import _render_frames

    T = args[5].shape[0]
    times, frames = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        frames = _render_frames(*args, background=(1.0, 1.0, 1.0), device=device, resident=resident)
        times.append((time.perf_counter() - t0) / T)
    return times, frames


def same_frames(a: list, b: list) -> bool:
    """Whether two lists of frames are equal bit for bit (rgb, depth, alpha)."""
    return len(a) == len(b) and all(np.array_equal(getattr(x, k), getattr(y, k))
                                    for x, y in zip(a, b) for k in ("rgb", "depth", "alpha"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0")
    ap.add_argument("--gaussians", type=int, default=584_000, help="Gaussians on the shell")
    ap.add_argument("--frames", type=int, default=8, help="frames of the motion")
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--repeats", type=int, default=3, help="renders of the motion per path (median)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if min(args.gaussians, args.frames, args.width, args.height, args.repeats) < 1:
        ap.error("--gaussians, --frames, --width, --height and --repeats must be positive")

    from knockgs_core._warp import warp_device
    from knockgs_core.render import Camera, project
    from knockgs_core.render._constants import tile_size_for

    dev = warp_device(args.device)
    rng = np.random.default_rng(args.seed)
    means, cov, colors, opac = shell_scene(args.gaussians, rng)
    pos, F = shear_motion(means, args.frames, rng)
    static = np.zeros(args.gaussians, bool)
    cam = Camera.look_at(CENTRE + [0.0, -1.3, 0.65], CENTRE, [0.0, 0.0, 1.0], fov_deg=40.0,
                         width=args.width, height=args.height)
    motion = (means, cov, colors, opac, static, pos, F, cam)
    warm = (means, cov, colors, opac, static, pos[:1], F[:1], cam)
    for resident in (False, True):  # kernels loaded (and compiled into an empty cache)
        time_path(warm, resident=resident, device=args.device, repeats=1)

    host, host_frames = time_path(motion, resident=False, device=args.device, repeats=args.repeats)
    res, res_frames = time_path(motion, resident=True, device=args.device, repeats=args.repeats)
    visible = int(project(means, cov, opac, cam, device=args.device).visible.sum())
    cover = float((res_frames[0].alpha > 0.5).mean())
    t_host, t_res = float(np.median(host)), float(np.median(res))
    print(f"{args.gaussians:,} Gaussians ({visible:,} visible at rest, {cover:.0%} of the pixels alpha > 0.5), "
          f"{args.frames} frames at {args.width}x{args.height} on {args.device} ({dev.name}), tile "
          f"{tile_size_for(dev, args.gaussians)} px; s a frame, median of {args.repeats}:")
    print(f"  host-binned     {t_host:.4f}  (runs: {', '.join(f'{x:.4f}' for x in host)})")
    print(f"  device-resident {t_res:.4f}  (runs: {', '.join(f'{x:.4f}' for x in res)})")
    print(f"  speed-up {t_host / t_res:.2f}x; frames identical: {same_frames(host_frames, res_frames)}")


if __name__ == "__main__":
    main()
