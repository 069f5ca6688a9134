"""An experiment, not a solver path: G2P fused with the next substep's P2G, each stencil node's
contributions summed across a warp by shuffles before one atomic per run of equal base cells.

The solver's GPU substep runs G2P fused with the next P2G's per-particle half (``g2p_prepare``:
it stores each particle's P2G terms) and then sums the terms by windows in shared memory
(``p2g_windows``). Here one kernel (``g2p2g_warp``) does both: a thread runs a particle's G2P and
its next P2G terms in registers; the particles are in cell order, so neighbouring lanes share
base cells; each lane finds the end of its run of equal keys (``__ballot_sync``), and every
stencil node's seven sums (momentum, mass, stress-free momentum) are reduced down the run by
``__shfl_down_sync`` (``segment_sum``, CUDA snippets through ``wp.func_native``); the run's
first lane adds them to the grid. The node velocities are read from one set of grids while the
sums go to another, swapped every substep, so a substep is: zero the other grids, the grid
update and supports, the fused kernel. No stored terms, no sort, no window kernel. On the CPU
the snippets fall back to runs of one particle (a per-particle scatter): there the pipeline
gives the non-fused scatter solver's displacements bit for bit (``--device cpu``).

Builds the object's model (particles in cell order), runs ``--warm`` substeps, then from one
saved state times ``--steps`` substeps of the solver's default GPU path (graphs) and of the
experiment (``--mode 1``: the 27 nodes in a loop; ``0``: unrolled) at each block size and
register cap, ``--repeats`` times, and compares the displacements.

    python3 benchmarks/warp_shuffle_experiment.py --object pillow --profile ci --device cpu --warm 60 --steps 10 --repeats 1
    python3 benchmarks/warp_shuffle_experiment.py --object pillow --particles OUT/pillow.npz --block 128 256 --regs 0 96 \
        --mode 0 --repeats 3
    python3 benchmarks/warp_shuffle_experiment.py --object ficus --particles OUT/ficus.npz --regs 0 128 --mode 1 --repeats 3
"""
import argparse
import time
from typing import Any

import numpy as np
import warp as wp

from knockgs_core.sim import _kernels as K
from knockgs_core.sim._kernels import (bspline_weights, g2p_particle, node_term, p2g_terms, stencil_base, stencil_inside,
                                       stencil_offset)

SEG = """
#if defined(__CUDA_ARCH__)
    unsigned int lane = threadIdx.x & 31u;
    int prev = __shfl_up_sync(0xffffffffu, key, 1);
    bool head = (lane == 0u) || (prev != key);
    unsigned int heads = __ballot_sync(0xffffffffu, head);
    unsigned int after = (lane == 31u) ? 0u : ((heads >> (lane + 1u)) << (lane + 1u));
    int end = after ? (__ffs(after) - 1) : 32;
    return (end - (int)lane) * 2 + (head ? 1 : 0);
#else
    return 3;
#endif
"""


@wp.func_native(SEG)
def warp_segment(key: int) -> int: ...


MAXSPAN = """
#if defined(__CUDA_ARCH__)
    return __reduce_max_sync(0xffffffffu, (unsigned int)span);
#else
    return span;
#endif
"""


@wp.func_native(MAXSPAN)
def warp_max(span: int) -> int: ...


SUM = """
#if defined(__CUDA_ARCH__)
    float v = x;
    for (int o = 1; o < top; o <<= 1) {
        float t = __shfl_down_sync(0xffffffffu, v, o);
        if (o < span) v += t;
    }
    return v;
#else
    return x;
#endif
"""


@wp.func_native(SUM)
def segment_sum(x: float, span: int, top: int) -> float: ...


def make_kernel(regs, mode):
    def g2p2g_warp(
        grid_v: wp.array(dtype=wp.vec3),
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
        mass: wp.array(dtype=float),
        vol: wp.array(dtype=float),
        mu: wp.array(dtype=float),
        lam: wp.array(dtype=float),
        probe_mask: wp.array(dtype=wp.int32),
        probe_force: wp.vec3,
        probe_on: int,
        polar_iters: int,
        polar_step: float,
        polar_rational: int,
        retardation: float,
        n_grid: int,
        none_key: int,
        count: int,
        nodes: int,
        u: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: Any,
        F: Any,
        rot: wp.array(dtype=wp.quat),
        overrun: wp.array(dtype=wp.int32),
        grid_mv: wp.array3d(dtype=wp.vec3),
        grid_m: wp.array3d(dtype=float),
        grid_mv_old: wp.array3d(dtype=wp.vec3),
    ):
        p = wp.tid()
        key = none_key
        f = wp.vec3(0.0)
        mvp = wp.vec3(0.0)
        m = float(0.0)
        aff = wp.mat33(0.0)
        mCp = wp.mat33(0.0)
        base = wp.vec3i(0)
        if p < count:
            ok, up, vp, Cp, Fp = g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo,
                                              hi, x0, affine_flip, flip_weight, grid_v_old, g2p_lines, u, v, C, F,
                                              overrun)
            if ok:
                m = mass[p]
                if probe_on == 1 and probe_mask[p] != 0:
                    vp = vp + probe_force * (dt / m)
                    v[p] = vp
                q, aff, mCp = p2g_terms(vp, Cp, Fp, rot[p], m, vol[p], mu[p], lam[p], inv_dx, dt, polar_iters,
                                        polar_step, polar_rational, retardation)
                rot[p] = q
                gx = (x0[p] + up) * inv_dx
                base = stencil_base(gx)
                if stencil_inside(base, lo, hi):
                    key = (base[0] * n_grid + base[1]) * n_grid + base[2]
                    f = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
                    mvp = m * vp
                else:
                    wp.atomic_add(overrun, 0, 1)
                    m = 0.0
        seg = warp_segment(key)
        span = seg // 2
        top = warp_max(span)
        lead = seg % 2 == 1 and key != none_key
        dx = 1.0 / inv_dx
        if wp.static(mode == 1):
            q4 = wp.vec4(mvp[0], mvp[1], mvp[2], m)
            g0 = base
            for n in range(nodes):
                o = stencil_offset(n)
                a, b, c = node_term(f, q4, aff, mCp, o[0], o[1], o[2], dx, affine_flip)
                a0 = segment_sum(a[0], span, top)
                a1 = segment_sum(a[1], span, top)
                a2 = segment_sum(a[2], span, top)
                bs = segment_sum(b, span, top)
                c0 = float(0.0)
                c1 = float(0.0)
                c2 = float(0.0)
                if affine_flip == 1:
                    c0 = segment_sum(c[0], span, top)
                    c1 = segment_sum(c[1], span, top)
                    c2 = segment_sum(c[2], span, top)
                if lead:
                    gi = g0[0] + o[0]
                    gj = g0[1] + o[1]
                    gk = g0[2] + o[2]
                    wp.atomic_add(grid_mv, gi, gj, gk, wp.vec3(a0, a1, a2))
                    wp.atomic_add(grid_m, gi, gj, gk, bs)
                    if affine_flip == 1:
                        wp.atomic_add(grid_mv_old, gi, gj, gk, wp.vec3(c0, c1, c2))
            return
        w = bspline_weights(f)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    dpos = (wp.vec3(float(i), float(j), float(k)) - f) * dx
                    a = weight * (mvp + aff * dpos)
                    b = weight * m
                    a0 = segment_sum(a[0], span, top)
                    a1 = segment_sum(a[1], span, top)
                    a2 = segment_sum(a[2], span, top)
                    bs = segment_sum(b, span, top)
                    c0 = float(0.0)
                    c1 = float(0.0)
                    c2 = float(0.0)
                    if affine_flip == 1:
                        c = weight * (mvp + mCp * dpos)
                        c0 = segment_sum(c[0], span, top)
                        c1 = segment_sum(c[1], span, top)
                        c2 = segment_sum(c[2], span, top)
                    if lead:
                        gi = base[0] + i
                        gj = base[1] + j
                        gk = base[2] + k
                        wp.atomic_add(grid_mv, gi, gj, gk, wp.vec3(a0, a1, a2))
                        wp.atomic_add(grid_m, gi, gj, gk, bs)
                        if affine_flip == 1:
                            wp.atomic_add(grid_mv_old, gi, gj, gk, wp.vec3(c0, c1, c2))

    return wp.kernel(g2p2g_warp, name=f"g2p2g_warp_{regs}_{mode}", cuda_max_registers=regs or None, module="unique")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--particles")
    ap.add_argument("--warm", type=int, default=300)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--block", type=int, nargs="+", default=[256])
    ap.add_argument("--regs", type=int, nargs="+", default=[0])
    ap.add_argument("--mode", type=int, nargs="+", default=[1])
    args = ap.parse_args()
    from _object_model import object_particles, probe_a_model

    from knockgs_core.contract import load_contract
    from knockgs_core.sim import MPMSolver, make_state

    contract = load_contract(args.object, args.profile)
    ps = object_particles(contract, args.particles)
    dev = args.device
    model = probe_a_model(contract, ps, dev)
    p = model.params
    n = model.particle_count
    state = make_state(model, ps.positions)
    solver = MPMSolver(model, p2g="cells", graph=False, fuse=False)
    solver.check(state)
    for _ in range(args.warm):
        solver.step(state)
        if state.step % p.guard_every == 0:
            solver.check(state)
    solver.check(state)
    wp.synchronize_device(dev)
    print(f"{args.object}: {n} particles, box {solver._lo}..{solver._hi}, step {state.step}, "
          f"probe steps {model.probe_first}..{model.probe_first + model.probe_steps}", flush=True)

    names = ["particle_u", "particle_v", "particle_C", "particle_F", "particle_rot", "grid_mv", "grid_m", "grid_mv_old"]

    def snapshot(s):
        return {k: wp.clone(getattr(s, k)) for k in names}

    def restore(s, snap):
        for k in names:
            wp.copy(getattr(s, k), snap[k])

    snap = snapshot(state)
    step0 = state.step
    # baseline: the solver's default GPU path (fused G2P + windows, graphs)
    base_solver = MPMSolver(model)
    print(f"baseline: p2g {base_solver.p2g}, sums {base_solver.cell_sums}, fuse {base_solver.fuse}, graph {base_solver.graph}")

    def run_base():
        restore(state, snap)
        state.step = step0
        base_solver._prepared = None
        base_solver._sorted_at = None
        base_solver._cmds_key = None
        base_solver._lo, base_solver._hi = solver._lo, solver._hi
        for _ in range(2):  # record and capture outside the timing
            base_solver.step(state)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            base_solver.step(state)
        wp.synchronize_device(dev)
        return (time.perf_counter() - t0) / args.steps

    # warp-sum pipeline: grids A (state's) and B, swapped every substep
    g = p.n_grid
    B = dict(grid_mv=wp.zeros((g, g, g), dtype=wp.vec3, device=dev), grid_m=wp.zeros((g, g, g), dtype=float, device=dev),
             grid_mv_old=wp.zeros((g, g, g), dtype=wp.vec3, device=dev))
    lo = wp.vec3i(*solver._lo)
    hi = wp.vec3i(*solver._hi)
    dims = tuple(h - low for low, h in zip(solver._lo, solver._hi))
    flip = int(p.transfer == "affine_flip")
    damping = p.grid_v_damping_scale ** (p.dt / p.damping_dt_ref) if p.grid_v_damping_scale < 1.0 else 1.0
    from knockgs_core.sim._config import DomainWalls
    fused_walls = p.boundaries[0] if p.boundaries and isinstance(p.boundaries[0], DomainWalls) else None
    wall_args = [1, p.n_grid, fused_walls.padding, int(fused_walls.mode == "sticky")] if fused_walls else [0, p.n_grid, 0, 0]
    others = [bc for bc in p.boundaries if bc is not fused_walls]
    print("other boundaries:", others)
    overrun = wp.zeros(1, dtype=wp.int32, device=dev)
    zero_mask = wp.zeros(n, dtype=wp.int32, device=dev)
    none_key = g * g * g
    padded = -(-n // 32) * 32

    def grids(which):
        if which == 0:
            return dict(grid_mv=state.grid_mv, grid_m=state.grid_m, grid_mv_old=state.grid_mv_old)
        return B

    def pipeline_substep(kernel, bd, src, dst, probe_next):
        S, D = grids(src), grids(dst)
        wp.launch(K.grid_zero, dim=dims, inputs=[lo, flip], outputs=[D["grid_mv"], D["grid_m"], D["grid_mv_old"]],
                  device=dev)
        wp.launch(K.grid_update, dim=dims, inputs=[lo, p.dt, wp.vec3(*p.gravity), damping, *wall_args, flip, S["grid_m"]],
                  outputs=[S["grid_mv"], S["grid_mv_old"]], device=dev)
        for bc in others:
            if isinstance(bc, DomainWalls):
                wp.launch(K.grid_bc_walls, dim=dims, inputs=[lo, p.n_grid, bc.padding, int(bc.mode == "sticky")],
                          outputs=[S["grid_mv"]], device=dev)
            else:
                assert bc.start_time <= 0 and bc.end_time == float("inf")
                box_args = [wp.vec3(*bc.box.center), wp.vec3(*bc.box.half_size), wp.vec3(*bc.velocity),
                            bc.friction_coefficient]
                wp.launch(K.grid_bc_cuboid, dim=dims, inputs=[lo, p.dx, *box_args], outputs=[S["grid_mv"]], device=dev)
        wp.launch(kernel, dim=padded, block_dim=bd,
                  inputs=[S["grid_mv"].flatten(), solver._inv_dx, p.dt, zero_mask, wp.vec3(0.0), 0, lo, hi,
                          state.particle_x0, flip, p.flip_weight, S["grid_mv_old"].flatten(),
                          solver._g2p_lines, model.particle_mass,
                          model.particle_vol, model.particle_mu, model.particle_lam, model.probe_mask,
                          wp.vec3(*model.probe_force), probe_next, solver.polar_iters, solver.polar_step,
                          solver._polar_rational, solver.retardation, g, none_key, n, 27],
                  outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F, state.particle_rot,
                           overrun, D["grid_mv"], D["grid_m"], D["grid_mv_old"]], device=dev)

    def probe(step):
        return int(model.probe_steps > 0 and model.probe_first <= step < model.probe_first + model.probe_steps)

    kernels = {(regs, mode): make_kernel(regs, mode) for regs in args.regs for mode in args.mode}

    def launch_one(graphs, src, bd, kernel):
        if graphs:
            wp.capture_launch(graphs[src])
        else:
            pipeline_substep(kernel, bd, src, 1 - src, 0)

    def run_warp(bd, kernel):
        restore(state, snap)
        # the first substep's P2G: the solver's scatter-free path, from a fresh solver
        s0 = MPMSolver(model, p2g="scatter" if not wp.get_device(dev).is_cuda else "cells", graph=False, fuse=False)
        s0._lo, s0._hi = solver._lo, solver._hi
        s0._record(state)
        st = step0
        # one whole substep
        s0._launch(state, st * p.dt, probe(st), (True,) * len(s0._cmds["bcs"]), True, prepared=False, probe_next=None)
        # that substep's G2P already ran; now P2G of the next substep by the plain scatter into A
        wp.launch(K.grid_zero, dim=dims, inputs=[lo, flip], outputs=[state.grid_mv, state.grid_m, state.grid_mv_old], device=dev)
        st += 1
        wp.launch(K.p2g, dim=n, inputs=[state.particle_x0, state.particle_u, state.particle_C, state.particle_F,
                                        model.particle_mass, model.particle_vol, model.particle_mu, model.particle_lam,
                                        model.probe_mask, wp.vec3(*model.probe_force), probe(st), solver._inv_dx, p.dt,
                                        solver.polar_iters, solver.polar_step, solver._polar_rational, solver.retardation, lo,
                                        hi, flip],
                  outputs=[state.particle_v, state.particle_rot, state.grid_mv, state.grid_m, state.grid_mv_old, overrun],
                  device=dev)
        # graphs of the two parities
        src = 0
        graphs = []
        cuda = wp.get_device(dev).is_cuda
        for par in range(2 if cuda else 0):
            with wp.ScopedCapture(device=dev) as cap:
                pipeline_substep(kernel, bd, par, 1 - par, 0)
            graphs.append(cap.graph)
        # probe on at warm end? keep probe_next as of the solver
        if probe(st + 1):
            print("note: probe active; prototype graphs have probe off", flush=True)
        launch_one(graphs, src, bd, kernel)  # one substep untimed: the baseline's count
        src = 1 - src
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        for i in range(args.steps):
            launch_one(graphs, src, bd, kernel)
            src = 1 - src
        wp.synchronize_device(dev)
        el = (time.perf_counter() - t0) / args.steps
        return el, src

    # correctness: both from the same state, compare u after steps (+1 of the first substep)
    res = {}
    for r in range(args.repeats):
        tb = run_base()
        res.setdefault("base", []).append(tb)
        u_base = state.particle_u.numpy().astype(np.float64)
        for bd in args.block:
            for regs, kernel in kernels.items():
                tw, src = run_warp(bd, kernel)
                res.setdefault(f"warp{bd}r{regs}", []).append(tw)
                u_warp = state.particle_u.numpy().astype(np.float64)
        runs = ", ".join(f"{k} {1e3 * v[-1]:.4f}" for k, v in res.items() if k != "base")
        print(f"repeat {r}: base {1e3 * tb:.4f} ms, {runs}", flush=True)
    rms = float(np.sqrt((u_base ** 2).sum(1).mean()))
    d = float(np.sqrt(((u_base - u_warp) ** 2).sum(1).mean()))
    print(f"u RMS {rms:.6e}; base vs warp RMS diff {d:.3e} ({d / rms:.2e} relative); overrun {int(overrun.numpy()[0])}")
    for k, v in res.items():
        print(f"{k}: median {1e3 * float(np.median(v)):.4f} ms/substep")
    for regs, kernel in kernels.items():
        try:
            q = wp.get_cuda_kernel_properties(kernel, device=dev)
            print("cap", regs, "registers", q["register_count"], "local", q["local_memory_size"])
        except Exception as e:  # noqa
            print("props:", e)


if __name__ == "__main__":
    main()
