"""Warp kernels of the rasterizer (private): one thread per Gaussian, one per pixel.

The same kernels run on CPU and CUDA; the device is chosen at launch.
"""

from __future__ import annotations

from typing import Any

import warp as wp

EXACT_FP = {"fuse_fp": False, "enable_backward": False}
"""Module options of :func:`deform_rows_kernel`: no fused multiply-add, so every float64 product
and sum is rounded as NumPy's elementwise operations round it (``_deform._deform``), on CPU and CUDA."""


@wp.kernel
def project_kernel(
    means: wp.array(dtype=wp.vec3f),
    covariances: wp.array(dtype=wp.mat33f),
    opacities: wp.array(dtype=wp.float32),
    rotation: wp.mat33f,
    translation: wp.vec3f,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    lim_x_neg: float,
    lim_x_pos: float,
    lim_y_neg: float,
    lim_y_pos: float,
    near: float,
    blur: float,
    alpha_min: float,
    means2d: wp.array(dtype=wp.vec2f),
    conics: wp.array(dtype=wp.vec3f),
    covs2d: wp.array(dtype=wp.vec3f),
    depths: wp.array(dtype=wp.float32),
    radii: wp.array(dtype=wp.vec2f),
):
    """EWA projection of Gaussian ``i``; ``radii[i] = (0, 0)`` marks a culled Gaussian."""
    i = wp.tid()
    p = rotation * means[i] + translation
    z = p[2]
    depths[i] = z
    radii[i] = wp.vec2f(0.0, 0.0)
    if z <= near:
        return
    means2d[i] = wp.vec2f(fx * p[0] / z + cx, fy * p[1] / z + cy)
    # Clamp the direction used in the Jacobian to 1.3x the field of view (3DGS / gsplat).
    tx = wp.clamp(p[0] / z, -lim_x_neg, lim_x_pos) * z
    ty = wp.clamp(p[1] / z, -lim_y_neg, lim_y_pos) * z
    jac = wp.mat33f(
        fx / z, 0.0, -fx * tx / (z * z),
        0.0, fy / z, -fy * ty / (z * z),
        0.0, 0.0, 0.0,
    )
    cov_cam = rotation * covariances[i] * wp.transpose(rotation)
    c2 = jac * cov_cam * wp.transpose(jac)
    a = c2[0, 0] + blur
    b = c2[0, 1]
    c = c2[1, 1] + blur
    covs2d[i] = wp.vec3f(a, b, c)
    det = a * c - b * b
    if det <= 0.0:
        return
    conics[i] = wp.vec3f(c / det, -b / det, a / det)
    o = opacities[i]
    if o < alpha_min:
        return
    # Opacity-aware extent (gsplat): alpha >= alpha_min only inside this ellipse.
    k = wp.sqrt(2.0 * wp.log(o / alpha_min))
    radii[i] = wp.vec2f(k * wp.sqrt(a), k * wp.sqrt(c))


@wp.kernel
def rasterize_kernel(
    means2d: wp.array(dtype=wp.vec2f),
    conics: wp.array(dtype=wp.vec3f),
    colors: wp.array(dtype=wp.vec3f),
    opacities: wp.array(dtype=wp.float32),
    depths: wp.array(dtype=wp.float32),
    gaussian_ids: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    tiles_x: int,
    tile_size: int,
    background: wp.vec3f,
    alpha_min: float,
    alpha_max: float,
    transmittance_min: float,
    out_rgb: wp.array2d(dtype=wp.vec3f),
    out_depth: wp.array2d(dtype=wp.float32),
    out_alpha: wp.array2d(dtype=wp.float32),
):
    """Front-to-back compositing of pixel ``(row, col)`` over its tile's sorted list."""
    row, col = wp.tid()
    px = float(col) + 0.5
    py = float(row) + 0.5
    tile = (row // tile_size) * tiles_x + col // tile_size
    T = float(1.0)
    rgb = wp.vec3f(0.0, 0.0, 0.0)
    d = float(0.0)
    for k in range(tile_start[tile], tile_end[tile]):
        g = gaussian_ids[k]
        m = means2d[g]
        q = conics[g]
        dx = m[0] - px
        dy = m[1] - py
        power = -0.5 * (q[0] * dx * dx + q[2] * dy * dy) - q[1] * dx * dy
        alpha = wp.min(alpha_max, opacities[g] * wp.exp(power))
        if alpha < alpha_min:
            continue
        next_T = T * (1.0 - alpha)
        if next_T < transmittance_min:
            break
        w = alpha * T
        rgb = rgb + w * colors[g]
        d = d + w * depths[g]
        T = next_T
    out_rgb[row, col] = rgb + T * background
    out_depth[row, col] = d
    out_alpha[row, col] = 1.0 - T


# -- tile binning on the device (same lists as the host sort in ``bin_tiles``) ----------
@wp.func
def tile_box(m: wp.vec2f, r: wp.vec2f, tile_size: int, tiles_x: int, tiles_y: int) -> wp.vec4i:
    """``(lo_x, lo_y, span_x, span_y)`` of the tiles holding a pixel centre inside
    ``m +- (r + 0.5)``; computed in float64 exactly as the host path."""
    ts = wp.float64(tile_size)
    half = wp.float64(0.5)
    lo = wp.vec2i(0, 0)
    span = wp.vec2i(0, 0)
    for a in range(2):
        ra = wp.float64(r[a]) + half
        ma = wp.float64(m[a])
        lim = tiles_x - 1
        if a == 1:
            lim = tiles_y - 1
        lf = wp.floor((ma - ra - half) / ts)
        hf = wp.floor((ma + ra - half) / ts)
        lf = wp.min(wp.max(lf, wp.float64(0.0)), wp.float64(lim + 1))
        hf = wp.min(wp.max(hf, wp.float64(-1.0)), wp.float64(lim))
        lo[a] = int(lf)
        span[a] = wp.max(int(hf) - int(lf) + 1, 0)
    return wp.vec4i(lo[0], lo[1], span[0], span[1])


@wp.kernel
def tile_count_kernel(
    order: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2f),
    radii: wp.array(dtype=wp.vec2f),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    counts: wp.array(dtype=wp.int32),
):
    """Number of tiles each Gaussian (in depth order) overlaps."""
    i = wp.tid()
    g = order[i]
    b = tile_box(means2d[g], radii[g], tile_size, tiles_x, tiles_y)
    counts[i] = b[2] * b[3]


@wp.kernel
def tile_emit_kernel(
    order: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2f),
    radii: wp.array(dtype=wp.vec2f),
    offsets: wp.array(dtype=wp.int32),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    tile_keys: wp.array(dtype=wp.int32),
    gaussian_ids: wp.array(dtype=wp.int32),
):
    """One (tile, Gaussian) pair per overlapped tile, written in depth order."""
    i = wp.tid()
    g = order[i]
    b = tile_box(means2d[g], radii[g], tile_size, tiles_x, tiles_y)
    k = offsets[i]
    for ty in range(b[1], b[1] + b[3]):
        for tx in range(b[0], b[0] + b[2]):
            tile_keys[k] = ty * tiles_x + tx
            gaussian_ids[k] = g
            k += 1


@wp.kernel
def tile_ranges_kernel(
    tile_keys: wp.array(dtype=wp.int32),
    total: int,
    starts: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
):
    """``[start, end)`` of each tile in the sorted keys (binary search, as searchsorted)."""
    t = wp.tid()
    lo = int(0)
    hi = total
    while lo < hi:  # first key >= t
        mid = (lo + hi) // 2
        if tile_keys[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    starts[t] = lo
    hi = total
    while lo < hi:  # first key > t
        mid = (lo + hi) // 2
        if tile_keys[mid] <= t:
            lo = mid + 1
        else:
            hi = mid
    ends[t] = lo


# -- the visible Gaussians in index order, on the device (``_frame.DeviceFrames``) --------
@wp.func
def is_visible(r: wp.vec2f) -> wp.int32:
    """1 where both radii [px] are positive (the Gaussian is not culled, as
    ``Projection.visible``), else 0 (NaN radii included)."""
    if r[0] > 0.0 and r[1] > 0.0:
        return 1
    return 0


@wp.kernel
def visible_flags_kernel(radii: wp.array(dtype=wp.vec2f), flags: wp.array(dtype=wp.int32)):
    """``flags[i]``: 1 if Gaussian ``i`` is visible, else 0 (``radii [>= N]``, launched over N)."""
    i = wp.tid()
    flags[i] = is_visible(radii[i])


@wp.kernel
def compact_visible_kernel(
    flags: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    depths: wp.array(dtype=wp.float32),
    sentinel: int,
    depth_keys: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
):
    """The visible Gaussians first, in increasing index order, with their depths as sort keys.

    ``flags [N]`` from :func:`visible_flags_kernel`; ``slots [N]`` their exclusive prefix sum
    (the slot of each visible Gaussian). Writes ``order[slots[i]] = i`` and ``depth_keys[slots[i]]
    = depths[i]`` for each visible ``i``; the slots from the visible count on get ``sentinel``
    (a Gaussian index whose box misses the image) with key ``+inf``, so that a stable sort by
    depth keeps them last. Launched over N; each slot is written by one thread.
    """
    i = wp.tid()
    n = flags.shape[0]
    n_visible = slots[n - 1] + flags[n - 1]
    if flags[i] != 0:
        depth_keys[slots[i]] = depths[i]
        order[slots[i]] = i
    if i >= n_visible:
        depth_keys[i] = wp.inf
        order[i] = sentinel


@wp.kernel
def pair_total_kernel(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), total: wp.array(dtype=wp.int32)):
    """``total[0]``: the number of (tile, Gaussian) pairs, the last exclusive offset plus its count."""
    n = counts.shape[0]
    total[0] = offsets[n - 1] + counts[n - 1]


# -- deformed covariances on the device (``render_frames``) ------------------------------
@wp.func
def deformed_covariance(F: wp.mat33d, cov0: wp.mat33d) -> wp.mat33d:
    """``0.5 (C + C^T)`` with ``C = (F cov0) F^T`` (PhysGaussian), float64.

    Every entry is summed in index order, ``(p0 + p1) + p2``, as the host ``_deform`` and the
    symmetrization of ``render`` do; compiled with :data:`EXACT_FP` (no FMA) it gives their bits.
    """
    a = wp.mat33d()
    for i in range(3):
        for j in range(3):
            a[i, j] = F[i, 0] * cov0[0, j] + F[i, 1] * cov0[1, j] + F[i, 2] * cov0[2, j]
    c = wp.mat33d()
    for i in range(3):
        for j in range(3):
            c[i, j] = a[i, 0] * F[j, 0] + a[i, 1] * F[j, 1] + a[i, 2] * F[j, 2]
    half = wp.float64(0.5)
    s = wp.mat33d()
    for i in range(3):
        for j in range(3):
            s[i, j] = half * (c[i, j] + c[j, i])
    return s


@wp.kernel(module="unique", module_options=EXACT_FP)
def deform_rows_kernel(
    frame: wp.array2d(dtype=Any),
    rows: wp.array(dtype=wp.int32),
    cov0: wp.array(dtype=wp.mat33d),
    means: wp.array(dtype=wp.vec3f),
    covariances: wp.array(dtype=wp.mat33f),
):
    """Simulated Gaussian ``i`` at one frame, written into the scene's float32 render buffers.

    ``frame [M, 12]`` (float32 or float64): the position [m] (3) then ``F`` row-major (9) of
    each simulated Gaussian; ``rows [M]``: its row in the scene; ``cov0 [M]``: its rest
    covariance. Writes ``means[rows[i]]`` and the symmetrized ``covariances[rows[i]]``
    (computed in float64, rounded once to float32, as the host path casts for ``project``).
    """
    i = wp.tid()
    r = rows[i]
    means[r] = wp.vec3f(wp.float32(frame[i, 0]), wp.float32(frame[i, 1]), wp.float32(frame[i, 2]))
    F = wp.mat33d(
        wp.float64(frame[i, 3]), wp.float64(frame[i, 4]), wp.float64(frame[i, 5]),
        wp.float64(frame[i, 6]), wp.float64(frame[i, 7]), wp.float64(frame[i, 8]),
        wp.float64(frame[i, 9]), wp.float64(frame[i, 10]), wp.float64(frame[i, 11]),
    )
    covariances[r] = wp.mat33f(deformed_covariance(F, cov0[i]))
