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
"""Tile edge [px] on the CPU, where a pixel's cost is the length of its tile's list and no
shared memory rewards big tiles: 4 px renders the Pillow 2.6x faster than 16 px, with
identical pixels (``benchmarks/README_render.md``)."""


def tile_size_for(device) -> int:
    """The tile edge used on a Warp ``device``."""
    return TILE_SIZE_CPU if device.is_cpu else TILE_SIZE


def jacobian_limits(camera):
    """``(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos)``: bounds on ``x/z`` and ``y/z``."""
    return (
        FOV_CLAMP * camera.cx / camera.fx,
        FOV_CLAMP * (camera.width - camera.cx) / camera.fx,
        FOV_CLAMP * camera.cy / camera.fy,
        FOV_CLAMP * (camera.height - camera.cy) / camera.fy,
    )
