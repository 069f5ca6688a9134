"""Particle-to-grid kernels of the solver: the scatter (one float atomic per particle and
stencil node) and the P2G by cells (per-particle terms, the sort keys, and the sums by windows
of sorted particles into the grid, the fixed-point sums or the node records)."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._grid import fixed_add, vec4_atomic_add
from ._math import (bspline_weights, fixed_corotated_kirchhoff, kelvin_voigt_kirchhoff, mat33_at,
                    mat33_from_rows, mat33_put, mat33_to_f32, mat33d_at, overload_per_layout, polar_rotation,
                    stencil_base, stencil_inside, vec4_head)
from . import _module
from ._module import MODULE


@wp.func(module=MODULE)
def p2g_terms(vp: wp.vec3, Cp: wp.mat33, Fd: wp.mat33d, q0: wp.quat, m: float, volp: float, mup: float, lamp: float,
              inv_dx: float, dt: float, polar_iters: int, polar_step: float, polar_rational: int, retardation: float):
    """A particle's stress and transfer terms from its velocity ``vp`` [m/s], affine matrix
    ``Cp`` [1/s], deformation gradient ``Fd`` (float64) and last rotation ``q0``: the
    warm-started rotation, the affine matrix of the transfer (stress and APIC terms) and its
    APIC term alone (fixed-corotated stress, plus the Kelvin-Voigt viscous stress when
    ``retardation`` [s] > 0)."""
    Fp = mat33_to_f32(Fd)
    q = polar_rotation(Fp, q0, polar_iters, polar_step, polar_rational)
    tau = fixed_corotated_kirchhoff(Fp, wp.quat_to_matrix(q), mup, lamp)
    if retardation > 0.0:
        tau = tau + kelvin_voigt_kirchhoff(Cp, wp.determinant(Fp), mup, lamp, retardation)
    mC = m * Cp
    affine = (-dt * volp * 4.0 * inv_dx * inv_dx) * tau + mC
    return q, affine, mC


@wp.func(module=MODULE)
def p2g_particle(
    p: int,
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_weight: wp.array(dtype=float),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
):
    """Particle ``p``'s part of P2G: the probe impulse (``v += w f / m dt``, ``w`` the
    particle's probe weight; written back), the
    warm-started rotation (written back) and :func:`p2g_terms`; returns the velocity,
    the affine matrix of the transfer (stress and APIC terms) and its APIC term alone."""
    m = mass[p]
    vp = v[p]
    if probe_on == 1 and probe_weight[p] != 0.0:
        vp = vp + probe_force * (probe_weight[p] * dt / m)
        v[p] = vp
    q, affine, mC = p2g_terms(vp, mat33_at(C, p), mat33d_at(F, p), rot[p], m, vol[p], mu[p], lam[p], inv_dx, dt,
                              polar_iters, polar_step, polar_rational, retardation)
    rot[p] = q
    return vp, affine, mC


@wp.kernel(module=MODULE)
def p2g(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_weight: wp.array(dtype=float),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    lo: wp.vec3i,
    hi: wp.vec3i,
    affine_flip: int,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
    overrun: wp.array(dtype=wp.int32),
):
    """Probe impulse (``v += f / m dt``), fixed-corotated stress, affine scatter to the grid;
    with ``affine_flip = 1`` also the momentum without the stress term into ``grid_mv_old``
    (the probe impulse is in both: it is the particle's velocity, not a grid force)."""
    p = wp.tid()
    m = mass[p]
    vp, affine, mC = p2g_particle(p, C, F, mass, vol, mu, lam, probe_weight, probe_force, probe_on, inv_dx, dt, polar_iters,
                                  polar_step, polar_rational, retardation, v, rot)
    dx = 1.0 / inv_dx

    gx = (x0[p] + u[p]) * inv_dx
    base = stencil_base(gx)
    if not stencil_inside(base, lo, hi):
        wp.atomic_add(overrun, 0, 1)
        return
    fx = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    w = bspline_weights(fx)
    mv = m * vp
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gi = base[0] + i
                gj = base[1] + j
                gk = base[2] + k
                wp.atomic_add(grid_mv, gi, gj, gk, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, gi, gj, gk, weight * m)
                if affine_flip == 1:
                    wp.atomic_add(grid_mv_old, gi, gj, gk, weight * (mv + mC * dpos))


# -- P2G by cells (the GPU path) ---------------------------------------------------------
# The scatter P2G above adds 27 contributions per particle to the grid with float atomics;
# where many particles share a cell (the paper-scale assets' shells: up to ~200 per cell) the
# GPU serializes those atomics on the shared nodes. By cells: each particle's contribution
# terms and the key of its stencil base cell are computed once, in the particles' own order
# (``p2g_prepare``); the particles are sorted by key (``p2g_sort_keys`` and a radix sort, every
# few substeps: between sorts a particle that changed cells only cuts its run short), and the
# sorted particles are summed by windows (:func:`p2g_windows`): one atomic per run of particles
# of one base cell and stencil node instead of one per particle. The same sums, in another
# order (float rounding differs from the scatter's).


@wp.func(module=MODULE)
def p2g_store(p: int, gx: wp.vec3, aff: wp.mat33, lo: wp.vec3i, hi: wp.vec3i, n_grid: int, none_key: int,
              fx: wp.array(dtype=wp.vec3), affine: Any, keys: wp.array(dtype=wp.int32),
              overrun: wp.array(dtype=wp.int32)):
    """Store particle ``p``'s P2G terms at grid position ``gx`` [cells] (see :func:`p2g_prepare`)."""
    base = stencil_base(gx)
    if stencil_inside(base, lo, hi):
        keys[p] = (base[0] * n_grid + base[1]) * n_grid + base[2]
        fx[p] = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        mat33_put(affine, p, aff)
    else:
        wp.atomic_add(overrun, 0, 1)
        keys[p] = none_key


@wp.kernel(module=MODULE)
def p2g_prepare(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_weight: wp.array(dtype=float),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    lo: wp.vec3i,
    hi: wp.vec3i,
    n_grid: int,
    none_key: int,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
    fx: wp.array(dtype=wp.vec3),
    affine: Any,
    keys: wp.array(dtype=wp.int32),
    overrun: wp.array(dtype=wp.int32),
):
    """The per-particle half of :func:`p2g` (:func:`p2g_particle`), in the particles' order:
    the position in the base cell ``fx`` [cells], the affine matrix of stress and APIC terms
    ``affine`` and the sort key ``keys``: the base cell's index, or ``none_key`` (above every
    cell's) outside the active box; the probe's impulse goes into ``v``. The momentum and mass
    and affine FLIP's APIC term alone, ``m C``, are not stored: the sums form them from the
    state's ``v`` and ``C`` and the model's mass (:func:`momentum_mass`, :func:`apic_term`),
    which stay as they are until G2P: the same products."""
    p = wp.tid()
    vp, aff, mCp = p2g_particle(p, C, F, mass, vol, mu, lam, probe_weight, probe_force, probe_on, inv_dx, dt, polar_iters,
                                polar_step, polar_rational, retardation, v, rot)
    p2g_store(p, (x0[p] + u[p]) * inv_dx, aff, lo, hi, n_grid, none_key, fx, affine, keys, overrun)


@wp.kernel(module=MODULE)
def p2g_sort_keys(keys: wp.array(dtype=wp.int32), sort_keys: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32)):
    """The radix sort's input: a copy of the keys and the identity order."""
    p = wp.tid()
    sort_keys[p] = keys[p]
    order[p] = p


@wp.func(module=MODULE)
def stencil_offset(n: int) -> wp.vec3i:
    """Stencil node ``n`` (0..26) of a base cell as its offset ``(i, j, k)``, ``n = 9 i + 3 j + k``."""
    return wp.vec3i(n // 9, (n // 3) % 3, n % 3)


@wp.func(module=MODULE)
def momentum_mass(v: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), p: int) -> wp.vec4:
    """Particle ``p``'s momentum [kg m/s] ([xyz]) and mass [kg] ([w]) for P2G, from the state's
    velocity (which holds this substep's probe impulse once the per-particle P2G half has run)
    and the model's mass: the product :func:`p2g_particle` forms, bit for bit, formed where it
    is summed instead of stored (a 16-byte write a particle and substep saved)."""
    m = mass[p]
    mvp = m * v[p]
    return wp.vec4(mvp[0], mvp[1], mvp[2], m)


@wp.func(module=MODULE)
def apic_term(q: wp.vec4, C: Any, p: int) -> wp.mat33:
    """Particle ``p``'s APIC term ``m C`` [kg/s] of the affine-FLIP transfer, from its momentum
    and mass ``q`` (:func:`momentum_mass`; mass in ``q[3]``) and the state's affine velocity
    ``C``: the product :func:`p2g_terms` forms, bit for bit, formed where it is summed instead
    of stored (a 36-byte write a particle and substep saved)."""
    return q[3] * mat33_at(C, p)


@wp.func(module=MODULE)
def node_term(weight: float, f: wp.vec3, q: wp.vec4, A: wp.mat33, M: wp.mat33, i: int, j: int, k: int, dx: float,
              affine_flip: int):
    """One particle's contribution to the stencil node ``(i, j, k)`` of its base cell, from its
    weight at the node ``weight`` (the product of its B-spline weights along x, y and z, in that
    order) and its P2G terms (position in the cell ``f`` [cells], momentum and mass ``q``, affine
    matrices ``A`` and ``M``): momentum [kg m/s], mass [kg], and the stress-free momentum (affine
    FLIP only, else 0)."""
    dpos = (wp.vec3(float(i), float(j), float(k)) - f) * dx
    mvp = wp.vec3(q[0], q[1], q[2])
    old = wp.vec3(0.0)
    if affine_flip == 1:
        old = weight * (mvp + M * dpos)
    return weight * (mvp + A * dpos), weight * q[3], old


# P2G by windows (W = ``SolverConfig.cell_chunk``): one block of ``W`` threads takes the ``W``
# sorted positions ``b W .. b W + W - 1``; its threads put those particles' terms in shared
# memory together, then each thread sums one run of equal keys (a window is cut where the key
# changes and at its ends) to one stencil node from shared memory, in slot order, and adds the
# sum with one atomic (:func:`window_sums`). Staging the terms once a window spares each of a
# run's threads a chain of dependent global loads through the sort's order (windows of other
# sizes measured in benchmarks/results/2026-11-27-window-sums-and-reference.md).
@wp.func(module=MODULE)
def window_run_sum(t_key: Any, t_end: Any, t_runs: Any, q: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any, t_mC: Any,
                   n_grid: int, dx: float, affine_flip: int):
    """The (run, stencil node) pair ``q`` (run ``q // 27``, node ``q % 27``) of a window's staged
    terms (see :func:`window_sums`): the run's :func:`node_term` summed to the node in slot
    order, and the node's index in the grid."""
    r = q // 27
    s = t_runs[r]
    e = t_end[s]
    key = t_key[s]
    n = q - 27 * r
    o = stencil_offset(n)
    sum_mv = wp.vec3(0.0)
    sum_m = float(0.0)
    sum_old = wp.vec3(0.0)
    for t in range(s, e):
        weight = t_w[t, o[0]] * t_w[t, 3 + o[1]] * t_w[t, 6 + o[2]]
        M = wp.mat33(0.0)
        if affine_flip == 1:
            M = mat33_from_rows(t_mC[t, 0], t_mC[t, 1], t_mC[t, 2])
        d_mv, d_m, d_old = node_term(weight, vec4_head(t_fx[t]), t_mv[t],
                                     mat33_from_rows(t_aff[t, 0], t_aff[t, 1], t_aff[t, 2]), M, o[0], o[1], o[2], dx,
                                     affine_flip)
        sum_mv += d_mv
        sum_m += d_m
        sum_old += d_old
    node = key + (o[0] * n_grid + o[1]) * n_grid + o[2]
    return node, sum_mv, sum_m, sum_old


@wp.func(module=MODULE)
def window_sums(t_key: Any, t_end: Any, t_runs: Any, runs: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any, t_mC: Any,
                lane: int, threads: int, n_grid: int, dx: float, affine_flip: int, grid_mv: wp.array(dtype=wp.vec3),
                grid_m: wp.array(dtype=float), grid_mv_old: wp.array(dtype=wp.vec3), records: int,
                sums_mvm: wp.array(dtype=wp.vec4), sums_old: wp.array(dtype=wp.vec4)):
    """A block's sums from its staged terms (shared-memory tiles of the window's slots: key, run
    end (:func:`window_run_end`), the weights ``t_w[slot, 3 axis + node]``, ``fx``, momentum and
    mass, and the rows of ``affine`` and ``m C``, each in a vec4: one 16-byte load where a vec3
    or a matrix's row would take three) and its ``runs`` runs' first slots ``t_runs`` (in slot
    order): the thread ``lane`` of ``threads`` takes the (run, stencil node) pairs ``lane, lane + threads,
    ...``; a run is the slots ``s .. t_end[s] - 1``, its :func:`node_term` summed to node ``n`` in
    slot order (:func:`window_run_sum`), and added to the grid
    (flat arrays of the ``n_grid``^3 nodes; a base cell's key is its node's index) with one
    atomic per array, or (``records = 1``) to the node records ``sums_mvm`` and ``sums_old``
    with one :func:`vec4_atomic_add` each."""
    for q in range(lane, runs * 27, threads):
        node, sum_mv, sum_m, sum_old = window_run_sum(t_key, t_end, t_runs, q, t_w, t_fx, t_mv, t_aff, t_mC, n_grid, dx,
                                                      affine_flip)
        if records == 1:
            vec4_atomic_add(sums_mvm, node, wp.vec4(sum_mv[0], sum_mv[1], sum_mv[2], sum_m))
            if affine_flip == 1:
                vec4_atomic_add(sums_old, node, wp.vec4(sum_old[0], sum_old[1], sum_old[2], 0.0))
        else:
            wp.atomic_add(grid_mv, node, sum_mv)
            wp.atomic_add(grid_m, node, sum_m)
            if affine_flip == 1:
                wp.atomic_add(grid_mv_old, node, sum_old)


@wp.func(module=MODULE)
def window_sums_fixed(t_key: Any, t_end: Any, t_runs: Any, runs: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any,
                      t_mC: Any, lane: int, threads: int, n_grid: int, dx: float, affine_flip: int,
                      q_sums: wp.array2d(dtype=wp.int64), scale_m: float, scale_p: float,
                      overflow: wp.array(dtype=wp.int32)):
    """:func:`window_sums` into the fixed-point sums ``q_sums`` (:func:`fixed_add`; mass in
    units of ``1 / scale_m``, momenta of ``1 / scale_p``): the same run sums, added in integers,
    so the nodes' sums do not depend on the order the runs arrive in."""
    for q in range(lane, runs * 27, threads):
        node, sum_mv, sum_m, sum_old = window_run_sum(t_key, t_end, t_runs, q, t_w, t_fx, t_mv, t_aff, t_mC, n_grid, dx,
                                                      affine_flip)
        for a in range(3):
            fixed_add(q_sums, a, node, sum_mv[a], scale_p, overflow)
        fixed_add(q_sums, 3, node, sum_m, scale_m, overflow)
        if affine_flip == 1:
            for a in range(3):
                fixed_add(q_sums, 4 + a, node, sum_old[a], scale_p, overflow)


@wp.func(module=MODULE)
def window_runs_before(t_end: Any, s: int, window: int) -> wp.vec2i:
    """How many runs start before slot ``s`` of a window (slots whose run end is not 0), and in
    the whole window."""
    before = int(0)
    total = int(0)
    for t in range(window):
        if t_end[t] != 0:
            if t < s:
                before += 1
            total += 1
    return wp.vec2i(before, total)


@_module.func_native("""#if defined(__CUDA_ARCH__)
const unsigned m = __ballot_sync(0xffffffffu, starts != 0);
return wp::vec2i(__popc(m & ((1u << (threadIdx.x & 31u)) - 1u)), __popc(m));
#else
return wp::vec2i(-1, -1);
#endif
""")
def warp_runs_before(starts: int) -> wp.vec2i:
    """:func:`window_runs_before` for a window of 32 slots held by one warp, a slot a lane
    (``starts``: a run starts at this lane's slot): the runs that start at the lanes below this
    one, and in the whole warp, from one ballot. ``(-1, -1)`` on the CPU, whose block is one
    thread (the caller counts there)."""
    ...


@_module.func_native("""#if defined(__CUDA_ARCH__)
const unsigned m = __ballot_sync(0xffffffffu, change != 0);
const unsigned lane = threadIdx.x & 31u;
if (!start) return 0;
const unsigned above = lane == 31u ? 0u : (m >> (lane + 1u));
return above ? (int)(lane + __ffs(above)) : 32;
#else
return -1;
#endif
""")
def warp_run_end(change: int, start: int) -> int:
    """:func:`window_run_end` for a window of 32 slots held by one warp, a slot a lane
    (``change``: this slot's key differs from the slot before's, or it is the first;
    ``start``: a run starts here): the next lane above whose key changes, or 32, from one
    ballot; 0 where no run starts. -1 on the CPU (the caller searches there)."""
    ...


@wp.func(module=MODULE)
def window_run_end(t_key: Any, s: int, window: int, none_key: int) -> int:
    """The end (one past the last slot) of the run of equal keys that starts at slot ``s`` of a
    window's staged keys, or 0 where no run starts there (the slot before holds the same key,
    or the slot is empty: ``none_key``). Found once per slot, not once per stencil node."""
    key = t_key[s]
    if key == none_key:
        return 0
    if s > 0:
        if t_key[s - 1] == key:
            return 0
    e = s + 1
    while e < window:
        if t_key[e] != key:
            break
        e += 1
    return e


_WINDOW_KERNELS: dict = {}


def p2g_windows(window: int, affine_flip: int, fixed: bool = False, records: bool = False):
    """The P2G-by-windows kernel for windows of ``window`` sorted positions under the transfer
    ``affine_flip`` (1: affine FLIP, 0: APIC). A tile's size is fixed when the kernel is
    compiled, and the transfer is made a constant of the kernel (its branches in the inner
    loop compiled away), so one kernel per size and transfer. Launch with
    ``wp.launch_tiled(..., dim=ceil(count / window), block_dim=window)``; the CPU runs it with
    one thread a block (the loops stride by the block's size), the same sums. ``fixed``: the
    run sums go into the fixed-point sums ``q`` (:func:`window_sums_fixed`) instead of the
    float grid arrays (each variant ignores the other's arguments); ``records``: into the node
    records ``sums_mvm`` and ``sums_old`` with vector atomics (:func:`vec4_atomic_add`)."""
    if fixed and records:
        raise ValueError("the window sums go into the fixed-point sums or the node records, not both")
    kernel = _WINDOW_KERNELS.get((window, affine_flip, fixed, records))
    if kernel is not None:
        return kernel

    # one kernel body, long: its three phases (staging, run ends, run starts) share the block's
    # shared-memory tiles, and the sums themselves are funcs (window_sums, window_sums_fixed)
    def p2g_windows_kernel(
        order: wp.array(dtype=wp.int32),
        keys: wp.array(dtype=wp.int32),
        none_key: int,
        count: int,
        n_grid: int,
        inv_dx: float,
        fx: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        mass: wp.array(dtype=float),
        affine: Any,
        C: Any,
        grid_mv: wp.array(dtype=wp.vec3),
        grid_m: wp.array(dtype=float),
        grid_mv_old: wp.array(dtype=wp.vec3),
        sums_mvm: wp.array(dtype=wp.vec4),
        sums_old: wp.array(dtype=wp.vec4),
        q_sums: wp.array2d(dtype=wp.int64),
        scale_m: float,
        scale_p: float,
        overflow: wp.array(dtype=wp.int32),
    ):
        """Block ``b`` stages the terms of the particles ``order[b W + slot]`` (slot
        ``0 .. W-1``; past ``count``: key ``none_key``) in shared memory, the B-spline weights
        of each (the node's weight is then three loads and two products), and sums them
        (:func:`window_sums`)."""
        b, lane = wp.tid()
        threads = wp.block_dim()
        s0 = b * wp.static(window)
        t_key = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        t_w = wp.tile_empty(shape=(wp.static(window), 9), dtype=float, storage="shared")
        t_fx = wp.tile_empty(shape=wp.static(window), dtype=wp.vec4, storage="shared")
        t_mv = wp.tile_empty(shape=wp.static(window), dtype=wp.vec4, storage="shared")
        t_aff = wp.tile_empty(shape=(wp.static(window), 3), dtype=wp.vec4, storage="shared")
        t_mC = wp.tile_empty(shape=(wp.static(window), 3), dtype=wp.vec4, storage="shared")
        for slot in range(lane, wp.static(window), threads):
            key = none_key
            p = int(0)
            if s0 + slot < count:
                p = order[s0 + slot]
                key = keys[p]
            q = momentum_mass(v, mass, p)
            f = fx[p]
            W = bspline_weights(f)
            wp.tile_scatter_masked(t_key, slot, key, True)
            for a in range(3):
                for n in range(3):
                    wp.tile_scatter_masked(t_w, slot, 3 * a + n, W[n, a], True)
            wp.tile_scatter_masked(t_fx, slot, wp.vec4(f[0], f[1], f[2], 0.0), True)
            wp.tile_scatter_masked(t_mv, slot, q, True)
            A = mat33_at(affine, p)
            for r in range(3):
                wp.tile_scatter_masked(t_aff, slot, r, wp.vec4(A[r, 0], A[r, 1], A[r, 2], 0.0), True)
            if wp.static(affine_flip == 1):
                M = apic_term(q, C, p)
                for r in range(3):
                    wp.tile_scatter_masked(t_mC, slot, r, wp.vec4(M[r, 0], M[r, 1], M[r, 2], 0.0), True)
        t_end = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        for slot in range(lane, wp.static(window), threads):
            e = int(-1)
            if wp.static(window == 32):  # a warp a window on a GPU: the run ends found by a ballot
                key = t_key[slot]
                change = int(1)
                if slot > 0:
                    change = int(t_key[slot - 1] != key)
                e = warp_run_end(change, int(change == 1 and key != none_key))
            if e < 0:
                e = window_run_end(t_key, slot, wp.static(window), none_key)
            wp.tile_scatter_masked(t_end, slot, e, True)
        # the runs' first slots listed in slot order, so the threads share out (run, node) pairs only
        t_runs = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        runs = int(0)
        for slot in range(lane, wp.static(window), threads):
            ranks = wp.vec2i(-1, -1)
            if wp.static(window == 32):  # a warp a window on a GPU: the runs counted by a ballot
                ranks = warp_runs_before(int(t_end[slot] != 0))
            if ranks[0] < 0:
                ranks = window_runs_before(t_end, slot, wp.static(window))
            wp.tile_scatter_masked(t_runs, ranks[0], slot, t_end[slot] != 0)
            runs = ranks[1]
        if wp.static(fixed):
            window_sums_fixed(t_key, t_end, t_runs, runs, t_w, t_fx, t_mv, t_aff, t_mC, lane, threads, n_grid,
                              1.0 / inv_dx, wp.static(affine_flip), q_sums, scale_m, scale_p, overflow)
        else:
            window_sums(t_key, t_end, t_runs, runs, t_w, t_fx, t_mv, t_aff, t_mC, lane, threads, n_grid, 1.0 / inv_dx,
                        wp.static(affine_flip), grid_mv, grid_m, grid_mv_old, wp.static(int(records)), sums_mvm, sums_old)

    name = (f"p2g_windows_{window}_{'affine_flip' if affine_flip == 1 else 'apic'}{'_fixed' if fixed else ''}"
            f"{'_records' if records else ''}")
    kernel = overload_per_layout(wp.Kernel(p2g_windows_kernel, key=name, module=MODULE),
                                 f32=("affine", "C"))
    _WINDOW_KERNELS[window, affine_flip, fixed, records] = kernel
    return kernel



# the kernels generic in the matrices' layout, with their overloads (see overload_per_layout;
# the windows' kernels get theirs where they are made)
overload_per_layout(p2g, f32=("C",), f64=("F",))
overload_per_layout(p2g_prepare, f32=("C", "affine"), f64=("F",))
