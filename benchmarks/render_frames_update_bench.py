"""``render_frames`` (scene resident on the device, the deformation as a Warp kernel) against
its previous host path (``F Sigma_0 F^T`` as stacked NumPy products, the whole scene cast to
float32 and copied per frame) and against rendering each frame's deformed scene
(``render(*deformed_scene(...))``): a random scene of N Gaussians (55 % static) moved over 4
frames at 160x120, medians of 3 runs. A second line times the per-frame scene update alone.
(Named ``render_frames_bench.py`` until that name went to the comparison of the host-binned and
device-resident frame paths.)

    python3 benchmarks/render_frames_update_bench.py --gaussians 200000 [--device cuda:0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def host_frames(means0, cov0, colors, opac, static, positions, F, cam, device):
    """The previous ``render_frames`` loop: per frame, the simulated rows deformed on the host
    (``(F @ Sigma_0) @ F^T``, float64), symmetrized, and the whole scene handed to ``_render``
    (float32 casts and host-to-device copies of every row)."""
    from knockgs_core.render._pipeline import _render

    bg = np.ones(3)
    dyn = np.flatnonzero(~static)
    means = means0.copy()
    covs = 0.5 * (cov0 + np.swapaxes(cov0, 1, 2))
    c0 = cov0[dyn]
    out = []
    for t in range(positions.shape[0]):
        Ft = np.asarray(F[t], dtype=np.float64)
        c = (Ft @ c0) @ np.swapaxes(Ft, 1, 2)
        means[dyn] = np.asarray(positions[t], dtype=np.float64)
        covs[dyn] = 0.5 * (c + np.swapaxes(c, 1, 2))
        out.append(_render(means, covs, colors, opac, cam, bg, device))
    return out


def time_updates(means0, cov0, colors, opac, static, positions, F, device, repeats):
    """Seconds a frame of the scene update alone: the host path (deform, symmetrize, float32
    casts and copies of the full scene's means and covariances) and the device path
    (``_DeviceScene.set_frame``: one copy of the frame's positions and F, the kernel)."""
    import warp as wp

    from knockgs_core._warp import warp_device
    from knockgs_core.render._deform import _DeviceScene

    dev = warp_device(device)
    dyn = np.flatnonzero(~static)
    T = positions.shape[0]
    means = means0.copy()
    covs = 0.5 * (cov0 + np.swapaxes(cov0, 1, 2))
    c0 = cov0[dyn]
    host, kernel = [], []
    scene = _DeviceScene(means0, cov0, colors, opac, dyn, wide=False, dev=dev)
    for _ in range(repeats):
        t0 = time.perf_counter()
        for t in range(T):
            Ft = np.asarray(F[t], dtype=np.float64)
            c = (Ft @ c0) @ np.swapaxes(Ft, 1, 2)
            means[dyn] = np.asarray(positions[t], dtype=np.float64)
            covs[dyn] = 0.5 * (c + np.swapaxes(c, 1, 2))
            wp.array(means.astype(np.float32), dtype=wp.vec3f, device=dev)
            wp.array(covs.astype(np.float32), dtype=wp.mat33f, device=dev)
        wp.synchronize_device(dev)
        host.append((time.perf_counter() - t0) / T)
        t0 = time.perf_counter()
        for t in range(T):
            scene.set_frame(positions[t], F[t])
        wp.synchronize_device(dev)
        kernel.append((time.perf_counter() - t0) / T)
    return float(np.median(host)), float(np.median(kernel))


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

    per_frame, previous, once = [], [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        a = [render(*deformed_scene(means, cov, colors, opac, pos[t], F[t], static), cam, device=args.device)
             for t in range(T)]
        per_frame.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        h = host_frames(means, cov, colors, opac, static, pos, F, cam, args.device)
        previous.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        b = render_frames(means, cov, colors, opac, static, pos, F, cam, device=args.device)
        once.append(time.perf_counter() - t0)
    same = all(np.array_equal(x.rgb, y.rgb) and np.array_equal(x.alpha, y.alpha) for x, y in zip(a, b))
    dh = max(float(np.abs(x.rgb - y.rgb).max()) for x, y in zip(h, b))
    t_old, t_prev, t_new = (float(np.median(v)) / T for v in (per_frame, previous, once))
    print(f"{n:,} Gaussians ({m:,} simulated) on {args.device}, s a frame: per frame render(*deformed_scene) "
          f"{t_old:.4f}, previous render_frames (host deformation) {t_prev:.4f}, render_frames {t_new:.4f} "
          f"({t_prev / t_new:.2f}x the previous, {t_old / t_new:.2f}x per frame); frames identical to "
          f"render(*deformed_scene): {same}; max |rgb| difference to the previous path {dh:.2g}")
    t_host, t_kernel = time_updates(means, cov, colors, opac, static, pos, F, args.device, args.repeats)
    print(f"scene update alone, s a frame: host deformation + full-scene casts and copies {t_host:.4f}, "
          f"device kernel (one copy of the frame's rows) {t_kernel:.4f} ({t_host / t_kernel:.1f}x)")


if __name__ == "__main__":
    main()
