"""Constants of the 3DGS rasterization rule, shared by the Warp path and the reference."""

NEAR_PLANE = 0.01
"""Gaussians with camera depth ``z <= NEAR_PLANE`` are culled."""

LOW_PASS = 0.3
"""Added to the diagonal of every projected 2D covariance [px^2] (3DGS anti-aliasing)."""

ALPHA_MIN = 1.0 / 255.0
"""A Gaussian contributes to a pixel only where its alpha is at least this."""

ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped to at most this."""

TRANSMITTANCE_MIN = 1e-4
"""Compositing stops before the transmittance would drop below this."""

FOV_CLAMP = 1.3
"""The Jacobian is evaluated at view directions clamped to 1.3x the half field of view."""

TILE_SIZE = 16
"""Tile edge [px] on CUDA (one thread block per tile's pixels, as in 3DGS)."""

TILE_SIZE_CPU = 4
"""Tile edge [px] on the CPU for small scenes, where a pixel's cost is the length of its
tile's list and no shared memory rewards big tiles: 4 px renders the Pillow 2.6x faster
than 16 px, with identical pixels (``benchmarks/results/2026-11-22-renderer.md``)."""

TILE_SIZE_CPU_LARGE = 8
"""Tile edge [px] on the CPU from ``CPU_LARGE_SCENE`` Gaussians on: binning then costs more
than the shorter lists save, and 8 px is about 1.5x faster than 4 px at 50k Gaussians."""

CPU_LARGE_SCENE = 20_000
"""Gaussian count from which the CPU uses ``TILE_SIZE_CPU_LARGE``."""


def tile_size_for(device, n_gaussians: int = 0) -> int:
    """The tile edge used on a Warp ``device`` for a scene of ``n_gaussians`` Gaussians
    (the pixels do not depend on it, only the speed)."""
    if not device.is_cpu:
        return TILE_SIZE
    return TILE_SIZE_CPU_LARGE if n_gaussians >= CPU_LARGE_SCENE else TILE_SIZE_CPU


def jacobian_limits(camera):
    """``(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos)``: bounds on ``x/z`` and ``y/z``."""
    return (
        FOV_CLAMP * camera.cx / camera.fx,
        FOV_CLAMP * (camera.width - camera.cx) / camera.fx,
        FOV_CLAMP * camera.cy / camera.fy,
        FOV_CLAMP * (camera.height - camera.cy) / camera.fy,
    )
