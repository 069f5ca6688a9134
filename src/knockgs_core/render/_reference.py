"""A slow, plain NumPy (float64) reference of the rasterizer, for tests on small scenes.

No tiles, no bounding boxes: every Gaussian is evaluated at every pixel, in one
global depth order (ties by Gaussian index). Because a Gaussian's alpha is below
1/255 outside its binning box, this gives the same image as the tiled Warp path.
"""

from __future__ import annotations

import numpy as np

from knockgs_core.errors import InputError

from . import _constants as C
from ._camera import Camera, RenderOutput
from ._checks import check_background, check_scene


def render_reference(
    means,
    covariances,
    colors,
    opacities,
    camera: Camera,
    *,
    background=(1.0, 1.0, 1.0),
) -> RenderOutput:
    """Reference for :func:`render` (same arguments and output; CPU, float64 inside).

    ``means: [N, 3]``, ``covariances: [N, 3, 3]``, ``colors: [N, 3]``, ``opacities: [N]``.
    Cost O(N H W): use on small scenes only.
    """
    src = "render.render_reference"
    means, covs, colors, opac = check_scene(means, covariances, colors, opacities, src)
    if not isinstance(camera, Camera):
        raise InputError(src, "camera", f"expected a Camera, got {type(camera).__name__}")
    bg = check_background(background, src)
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))
    h, w = camera.height, camera.width
    R, t = camera.rotation, camera.translation
    lim_xn, lim_xp, lim_yn, lim_yp = C.jacobian_limits(camera)

    rgb = np.zeros((h, w, 3))
    depth = np.zeros((h, w))
    T = np.ones((h, w))
    done = np.zeros((h, w), dtype=bool)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # pixel centres

    p_cam = means @ R.T + t
    for i in np.argsort(p_cam[:, 2], kind="stable"):
        x, y, z = p_cam[i]
        if z <= C.NEAR_PLANE or opac[i] < C.ALPHA_MIN:
            continue
        tx = np.clip(x / z, -lim_xn, lim_xp) * z
        ty = np.clip(y / z, -lim_yn, lim_yp) * z
        J = np.array([
            [camera.fx / z, 0.0, -camera.fx * tx / z**2],
            [0.0, camera.fy / z, -camera.fy * ty / z**2],
        ])
        cov2d = J @ R @ covs[i] @ R.T @ J.T + C.LOW_PASS * np.eye(2)
        if np.linalg.det(cov2d) <= 0:
            continue
        inv = np.linalg.inv(cov2d)
        du = u - (camera.fx * x / z + camera.cx)
        dv = v - (camera.fy * y / z + camera.cy)
        maha = inv[0, 0] * du * du + 2 * inv[0, 1] * du * dv + inv[1, 1] * dv * dv
        alpha = np.minimum(C.ALPHA_MAX, opac[i] * np.exp(-0.5 * maha))
        active = ~done & (alpha >= C.ALPHA_MIN)
        next_T = T * (1.0 - alpha)
        stop = active & (next_T < C.TRANSMITTANCE_MIN)
        done |= stop
        add = active & ~stop
        weight = np.where(add, alpha * T, 0.0)
        rgb += weight[..., None] * colors[i]
        depth += weight * z
        T = np.where(add, next_T, T)
    rgb += T[..., None] * bg
    return RenderOutput(
        rgb=rgb.astype(np.float32), depth=depth.astype(np.float32), alpha=(1.0 - T).astype(np.float32)
    )
