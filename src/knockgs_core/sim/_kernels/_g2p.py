"""Grid-to-particle kernels of the solver: the gathers of the node velocities (node by node, or
along the stencil's lines), G2P, and G2P fused with the next substep's per-particle P2G half."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._math import (bspline_weights, mat33_at, mat33_put, mat33_to_f64, mat33d_at, mat33d_put, overload_per_layout, stencil_base,
                    stencil_inside)
from ._module import CUDA_MAX_REGISTERS, MODULE
from ._p2g import p2g_store, p2g_terms


@wp.func(module=MODULE)
def gather_by_nodes(grid_v: wp.array(dtype=wp.vec3), grid_v_old: wp.array(dtype=wp.vec3), origin: int, n_grid: int,
                    fx: wp.vec3, inv_dx: float, affine_flip: int):
    """G2P's gather, node by node: the velocity ``sum w v`` [m/s] and affine matrix ``4 / dx sum w
    v (x_i - x_p)^T`` [1/s] from the node velocities ``grid_v`` (flat arrays of the ``n_grid``^3
    grid, the stencil's first node at ``origin``) for the position ``fx`` in the base cell
    [cells]; with ``affine_flip = 1`` the same sums of the increments ``grid_v - grid_v_old``
    too (zero otherwise). An outer product a node: 54 multiply-adds a node under affine FLIP."""
    w = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    dv = wp.vec3(0.0)
    dC = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                dpos = wp.vec3(float(i), float(j), float(k)) - fx
                node = origin + (i * n_grid + j) * n_grid + k
                gv = grid_v[node]
                new_v = new_v + weight * gv
                new_C = new_C + (4.0 * inv_dx * weight) * wp.outer(gv, dpos)
                if affine_flip == 1:
                    du = gv - grid_v_old[node]
                    dv = dv + weight * du
                    dC = dC + (4.0 * inv_dx * weight) * wp.outer(du, dpos)
    return new_v, new_C, dv, dC


@wp.func(module=MODULE)
def columns_to_mat33(c0: wp.vec3, c1: wp.vec3, c2: wp.vec3, scale: float) -> wp.mat33:
    """The matrix of columns ``scale c0``, ``scale c1``, ``scale c2``."""
    return scale * wp.mat33(c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])


@wp.func(module=MODULE)
def fold_line(v: wp.vec3, c0: wp.vec3, c1: wp.vec3, c2: wp.vec3, line_w: wp.vec3, line_d: wp.vec3, wi: float,
              wj: float, di: float, dj: float):
    """Add a stencil line's sums (``line_w``: weighted by ``w_z``, ``line_d``: by ``w_z d_z``) to
    the gather's velocity and affine columns, with the line's x and y weights ``wi``, ``wj``
    and their offset-weighted ``di = wi d_x``, ``dj = wj d_y`` (:func:`gather_by_lines`)."""
    wij = wi * wj
    return v + wij * line_w, c0 + (di * wj) * line_w, c1 + (wi * dj) * line_w, c2 + wij * line_d


@wp.func(module=MODULE)
def gather_by_lines(grid_v: wp.array(dtype=wp.vec3), grid_v_old: wp.array(dtype=wp.vec3), origin: int, n_grid: int,
                    fx: wp.vec3, inv_dx: float, affine_flip: int):
    """:func:`gather_by_nodes`'s sums factored along the stencil's lines. The weight and the
    offset ``x_i - x_p`` of a node are products over the axes, so column ``a`` of the affine
    matrix is ``sum w_x w_y w_z d_a v`` with ``d_a = (o_a - fx_a)`` taken into axis ``a``'s
    weight: a line of three nodes along z is summed with the weights ``w_z`` and ``w_z d_z``
    (six multiply-adds a node), and the two line sums then enter the four sums with the line's
    x and y weights (twelve a line): ~300 multiply-adds a particle and field instead of ~700.
    The same sums in another order (float rounding apart)."""
    w = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    c0 = wp.vec3(0.0)
    c1 = wp.vec3(0.0)
    c2 = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    e0 = wp.vec3(0.0)
    e1 = wp.vec3(0.0)
    e2 = wp.vec3(0.0)
    for i in range(3):
        wi = w[i, 0]
        di = wi * (float(i) - fx[0])
        for j in range(3):
            wj = w[j, 1]
            dj = wj * (float(j) - fx[1])
            row = origin + (i * n_grid + j) * n_grid
            line_v = wp.vec3(0.0)
            line_d = wp.vec3(0.0)
            line_dv = wp.vec3(0.0)
            line_dd = wp.vec3(0.0)
            for k in range(3):
                wk = w[k, 2]
                dk = wk * (float(k) - fx[2])
                gv = grid_v[row + k]
                line_v = line_v + wk * gv
                line_d = line_d + dk * gv
                if affine_flip == 1:
                    du = gv - grid_v_old[row + k]
                    line_dv = line_dv + wk * du
                    line_dd = line_dd + dk * du
            new_v, c0, c1, c2 = fold_line(new_v, c0, c1, c2, line_v, line_d, wi, wj, di, dj)
            if affine_flip == 1:
                dv, e0, e1, e2 = fold_line(dv, e0, e1, e2, line_dv, line_dd, wi, wj, di, dj)
    return new_v, columns_to_mat33(c0, c1, c2, 4.0 * inv_dx), dv, columns_to_mat33(e0, e1, e2, 4.0 * inv_dx)


@wp.func(module=MODULE)
def g2p_particle(
    p: int,
    grid_v: wp.array(dtype=wp.vec3),
    n_grid: int,
    inv_dx: float,
    dt: float,
    trans_mask: wp.array(dtype=wp.int32),
    trans_velocity: wp.vec3,
    trans_on: int,
    lo: wp.vec3i,
    hi: wp.vec3i,
    x0: wp.array(dtype=wp.vec3),
    affine_flip: int,
    flip_weight: float,
    grid_v_old: wp.array(dtype=wp.vec3),
    g2p_lines: int,
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    overrun: wp.array(dtype=wp.int32),
):
    """Particle ``p``'s G2P (see :func:`g2p`), written back; returns whether its stencil lay
    inside the active box and the new displacement, velocity, affine matrix and F. The node
    velocities ``grid_v`` and ``grid_v_old`` are read as flat arrays of the (``n_grid``)^3 grid
    (node ``(i, j, k)`` at ``(i n_grid + j) n_grid + k``): one index a node from the stencil's
    first, instead of three with their checks. ``g2p_lines = 1`` gathers by stencil lines
    (:func:`gather_by_lines`), 0 node by node (:func:`gather_by_nodes`)."""
    up = u[p]
    gx = (x0[p] + up) * inv_dx
    base = stencil_base(gx)
    if not stencil_inside(base, lo, hi):
        wp.atomic_add(overrun, 0, 1)
        return False, up, v[p], mat33_at(C, p), mat33d_at(F, p)
    fx = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    origin = (base[0] * n_grid + base[1]) * n_grid + base[2]
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    dv = wp.vec3(0.0)
    dC = wp.mat33(0.0)
    if g2p_lines == 1:
        new_v, new_C, dv, dC = gather_by_lines(grid_v, grid_v_old, origin, n_grid, fx, inv_dx, affine_flip)
    else:
        new_v, new_C, dv, dC = gather_by_nodes(grid_v, grid_v_old, origin, n_grid, fx, inv_dx, affine_flip)
    held = trans_on == 1 and trans_mask[p] != 0
    if held:  # a prescribed motion: v and C take it exactly, under either transfer
        new_v = trans_velocity
        new_C = wp.mat33(0.0)
    Fp = (wp.identity(n=3, dtype=wp.float64) + wp.float64(dt) * mat33_to_f64(new_C)) * mat33d_at(F, p)
    mat33d_put(F, p, Fp)
    up = up + dt * new_v
    u[p] = up
    vp = new_v
    Cp = new_C
    if affine_flip == 1 and not held:
        vp = flip_weight * (v[p] + dv) + (1.0 - flip_weight) * new_v
        Cp = flip_weight * (mat33_at(C, p) + dC) + (1.0 - flip_weight) * new_C
    v[p] = vp
    mat33_put(C, p, Cp)
    return True, up, vp, Cp, Fp


@wp.kernel(cuda_max_registers=CUDA_MAX_REGISTERS, module=MODULE)
def g2p(
    grid_v: wp.array(dtype=wp.vec3),
    n_grid: int,
    inv_dx: float,
    dt: float,
    trans_mask: wp.array(dtype=wp.int32),
    trans_velocity: wp.vec3,
    trans_on: int,
    lo: wp.vec3i,
    hi: wp.vec3i,
    x0: wp.array(dtype=wp.vec3),
    affine_flip: int,
    flip_weight: float,
    grid_v_old: wp.array(dtype=wp.vec3),
    g2p_lines: int,
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    overrun: wp.array(dtype=wp.int32),
):
    """Gather (node velocities as flat arrays of the ``n_grid``^3 grid): new velocity and
    affine matrix (APIC, or with ``affine_flip = 1`` the affine FLIP update of weight
    ``flip_weight = exp(-dt / tau)`` with the old node velocities
    ``grid_v_old`` [m/s]), F <- (I + dt C_pic) F (F in float64), advect with the grid velocity
    ``v_pic``.

    Positions are rest position ``x0`` plus displacement ``u``; advecting the (small)
    displacement keeps sub-ulp motion that ``x += dt v`` in float32 near x = 1 would round
    away (a creep or a freeze of one ulp per substep)."""
    p = wp.tid()
    g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo, hi, x0, affine_flip,
                 flip_weight, grid_v_old, g2p_lines, u, v, C, F, overrun)


_G2P_PREPARE_KERNELS: dict = {}


def g2p_prepare(affine_flip: int) -> wp.Kernel:
    """The fused G2P kernel (:func:`g2p` with the next substep's :func:`p2g_prepare`) under the
    transfer ``affine_flip`` (1: affine FLIP, 0: APIC), made a constant of the kernel, as the
    windows' kernels are: APIC's kernel then holds neither the old node velocities' sums nor
    their registers. One kernel per transfer, its overloads per matrix layout made with it."""
    kernel = _G2P_PREPARE_KERNELS.get(affine_flip)
    if kernel is not None:
        return kernel

    def g2p_prepare_kernel(
        grid_v: wp.array(dtype=wp.vec3),
        inv_dx: float,
        dt: float,
        trans_mask: wp.array(dtype=wp.int32),
        trans_velocity: wp.vec3,
        trans_on: int,
        lo: wp.vec3i,
        hi: wp.vec3i,
        x0: wp.array(dtype=wp.vec3),
        flip_weight: float,
        grid_v_old: wp.array(dtype=wp.vec3),
        g2p_lines: int,
        mass: wp.array(dtype=float),
        vol: wp.array(dtype=float),
        mu: wp.array(dtype=float),
        lam: wp.array(dtype=float),
        probe_weight: wp.array(dtype=float),
        probe_force: wp.vec3,
        probe_on: int,
        polar_iters: int,
        polar_step: float,
        polar_rational: int,
        retardation: float,
        n_grid: int,
        none_key: int,
        u: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: Any,
        F: Any,
        rot: wp.array(dtype=wp.quat),
        fx: wp.array(dtype=wp.vec3),
        affine: Any,
        keys: wp.array(dtype=wp.int32),
        overrun: wp.array(dtype=wp.int32),
    ):
        """:func:`g2p` fused with the next substep's :func:`p2g_prepare` (its probe state
        ``probe_on``): the new velocity, affine matrix, F and position go from registers into
        the next P2G terms instead of being read back. The same arithmetic as the two kernels
        in turn, so the same bits."""
        p = wp.tid()
        ok, up, vp, Cp, Fp = g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo, hi,
                                          x0, wp.static(affine_flip), flip_weight, grid_v_old, g2p_lines, u, v, C, F,
                                          overrun)
        if ok:
            m = mass[p]
            if probe_on == 1 and probe_weight[p] != 0.0:
                vp = vp + probe_force * (probe_weight[p] * dt / m)
                v[p] = vp
            q, aff, mCp = p2g_terms(vp, Cp, Fp, rot[p], m, vol[p], mu[p], lam[p], inv_dx, dt, polar_iters, polar_step,
                                    polar_rational, retardation)
            rot[p] = q
            p2g_store(p, (x0[p] + up) * inv_dx, aff, lo, hi, n_grid, none_key, fx, affine, keys, overrun)
        else:
            keys[p] = none_key

    name = f"g2p_prepare_{'affine_flip' if affine_flip == 1 else 'apic'}"
    kernel = overload_per_layout(wp.Kernel(g2p_prepare_kernel, key=name, module=MODULE,
                                           options={"cuda_max_registers": CUDA_MAX_REGISTERS}),
                                 f32=("C", "affine"), f64=("F",))
    _G2P_PREPARE_KERNELS[affine_flip] = kernel
    return kernel



# the kernels generic in the matrices' layout, with their overloads (see overload_per_layout),
# and the fused G2P of both transfers, made with the module
overload_per_layout(g2p, f32=("C",), f64=("F",))
for _flip in (0, 1):
    g2p_prepare(_flip)
