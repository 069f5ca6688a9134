"""Kernels over the particle state as a whole: its rest state, the export gathers and the
guard's statistics."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._math import mat33_to_f32, mat33d_at, mat33d_put, overload_per_layout
from ._module import MODULE


@wp.kernel(module=MODULE)
def state_rest(F: Any, rot: wp.array(dtype=wp.quat)):
    """A particle at rest in its reference shape: ``F = I`` and its rotation the identity
    (the initial state, set on the device: no host array, no copy)."""
    p = wp.tid()
    mat33d_put(F, p, wp.identity(n=3, dtype=wp.float64))
    rot[p] = wp.quat_identity()



@wp.kernel(module=MODULE)
def gather_positions(x0: wp.array(dtype=wp.vec3), u: wp.array(dtype=wp.vec3), index: wp.array(dtype=wp.int32),
                     out: wp.array(dtype=wp.vec3)):
    """Export row ``i``: the position x0 + u of particle ``index[i]`` [m]."""
    i = wp.tid()
    p = index[i]
    out[i] = x0[p] + u[p]


@wp.kernel(module=MODULE)
def gather_F(F: Any, index: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.mat33)):
    """Export row ``i``: the deformation gradient of particle ``index[i]``, in float32."""
    i = wp.tid()
    out[i] = mat33_to_f32(mat33d_at(F, index[i]))


#: particles a block of the guard's statistics covers (its threads stride over them)
STATS_PER_BLOCK = 1024
#: threads a block of the guard's statistics (on a GPU; the CPU runs one a block)
STATS_BLOCK_DIM = 256


@wp.kernel(module=MODULE)
def guard_reset(out_f: wp.array(dtype=float), out_i: wp.array(dtype=wp.int32)):
    """The guard statistics' starting values (see :func:`particle_stats`), set on the device."""
    big = int(2147483647)
    out_f[0] = 0.0
    out_f[1] = wp.inf
    for a in range(3):
        out_i[1 + a] = big
        out_i[4 + a] = -big
    out_i[0] = 0
    out_i[7] = 0
    out_i[8] = 0


@wp.kernel(module=MODULE)
def particle_stats(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    F: Any,
    inv_dx: float,
    count: int,
    per_block: int,
    overrun: wp.array(dtype=wp.int32),
    overflow: wp.array(dtype=wp.int32),
    out_f: wp.array(dtype=float),
    out_i: wp.array(dtype=wp.int32),
):
    """Guard statistics of the particles ``b per_block .. (b + 1) per_block - 1`` in block
    ``b`` (its threads stride over them, then the block reduces its threads' values: one atomic
    a block and statistic, not one a particle, on a single address): out_f[0] = max |v|^2
    [m^2/s^2], out_f[1] = min det F; out_i[0] = non-finite count, out_i[1:4] = min cell,
    out_i[4:7] = max cell, and from block 0 the G2P overrun flag ``overrun[0]`` in out_i[7]
    and the reproducible P2G's ``overflow[0]`` in out_i[8] (one read-back for all). Maxima,
    minima and counts: the same values in any order. Start from :func:`guard_reset`; launch
    tiled over ``ceil(count / per_block)`` blocks."""
    b, lane = wp.tid()
    threads = wp.block_dim()
    big = int(2147483647)
    v2 = float(0.0)
    det = float(wp.inf)
    bad = int(0)
    lo0 = big
    lo1 = big
    lo2 = big
    hi0 = -big
    hi1 = -big
    hi2 = -big
    for p in range(b * per_block + lane, wp.min((b + 1) * per_block, count), threads):
        xp = x0[p] + u[p]
        vp = v[p]
        Fp = mat33_to_f32(mat33d_at(F, p))
        s = xp[0] + xp[1] + xp[2] + vp[0] + vp[1] + vp[2]
        for a in range(3):
            for c in range(3):
                s = s + Fp[a, c]
        if not wp.isfinite(s):
            bad += 1
            continue
        v2 = wp.max(v2, wp.dot(vp, vp))
        det = wp.min(det, wp.determinant(Fp))
        c0 = int(wp.floor(xp[0] * inv_dx))
        c1 = int(wp.floor(xp[1] * inv_dx))
        c2 = int(wp.floor(xp[2] * inv_dx))
        lo0 = wp.min(lo0, c0)
        lo1 = wp.min(lo1, c1)
        lo2 = wp.min(lo2, c2)
        hi0 = wp.max(hi0, c0)
        hi1 = wp.max(hi1, c1)
        hi2 = wp.max(hi2, c2)
    t_v2 = wp.tile_max(wp.tile(v2))
    t_det = wp.tile_min(wp.tile(det))
    t_bad = wp.tile_sum(wp.tile(bad))
    t_lo0 = wp.tile_min(wp.tile(lo0))
    t_lo1 = wp.tile_min(wp.tile(lo1))
    t_lo2 = wp.tile_min(wp.tile(lo2))
    t_hi0 = wp.tile_max(wp.tile(hi0))
    t_hi1 = wp.tile_max(wp.tile(hi1))
    t_hi2 = wp.tile_max(wp.tile(hi2))
    if lane == 0:
        wp.atomic_max(out_f, 0, t_v2[0])
        wp.atomic_min(out_f, 1, t_det[0])
        if t_bad[0] > 0:
            wp.atomic_add(out_i, 0, t_bad[0])
        wp.atomic_min(out_i, 1, t_lo0[0])
        wp.atomic_min(out_i, 2, t_lo1[0])
        wp.atomic_min(out_i, 3, t_lo2[0])
        wp.atomic_max(out_i, 4, t_hi0[0])
        wp.atomic_max(out_i, 5, t_hi1[0])
        wp.atomic_max(out_i, 6, t_hi2[0])
        if b == 0:
            out_i[7] = overrun[0]
            out_i[8] = overflow[0]



# the kernels generic in the matrices' layout, with their overloads (see overload_per_layout)
overload_per_layout(state_rest, f64=("F",))
overload_per_layout(gather_F, f64=("F",))
overload_per_layout(particle_stats, f64=("F",))
