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
from typing import Any

import numpy as np
import warp as wp
from _fused_pipeline import FusedPipeline, g2p_next_terms

from knockgs_core.sim._kernels import bspline_weights, node_term, stencil_offset

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
        valid, base, f, mvp, m, aff, mCp = g2p_next_terms(p, count, grid_v, inv_dx, dt, trans_mask, trans_velocity,
                                                          trans_on, lo, hi, x0, affine_flip, flip_weight, grid_v_old,
                                                          g2p_lines, mass, vol, mu, lam, probe_mask, probe_force, probe_on,
                                                          polar_iters, polar_step, polar_rational, retardation, n_grid,
                                                          u, v, C, F, rot, overrun)
        key = none_key
        if valid:
            key = (base[0] * n_grid + base[1]) * n_grid + base[2]
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
    pipe = FusedPipeline(model, state, solver)
    b = pipe.base
    print(f"baseline: p2g {b.p2g}, sums {b.cell_sums}, fuse {b.fuse}, graph {b.graph}")
    print("other boundaries:", pipe.others)
    g = p.n_grid
    none_key = g * g * g
    padded = -(-n // 32) * 32

    def launcher(kernel, bd):
        def fused(S, D):
            wp.launch(kernel, dim=padded, block_dim=bd,
                      inputs=[S["grid_mv"].flatten(), solver._inv_dx, p.dt, pipe.zero_mask, wp.vec3(0.0), 0, pipe.lo,
                              pipe.hi, state.particle_x0, pipe.flip, p.flip_weight, S["grid_mv_old"].flatten(),
                              solver._g2p_lines, model.particle_mass, model.particle_vol, model.particle_mu,
                              model.particle_lam, model.probe_mask, wp.vec3(*model.probe_force), 0, solver.polar_iters,
                              solver.polar_step, solver._polar_rational, solver.retardation, g, none_key, n, 27],
                      outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F,
                               state.particle_rot, pipe.overrun, D["grid_mv"], D["grid_m"], D["grid_mv_old"]], device=dev)
        return fused

    kernels = {(regs, mode): make_kernel(regs, mode) for regs in args.regs for mode in args.mode}
    first_p2g = "cells" if pipe.cuda else "scatter"
    # correctness: both from the same state, compare u after the timed substeps
    res = {}
    for r in range(args.repeats):
        tb = pipe.time_base(args.steps)
        res.setdefault("base", []).append(tb)
        u_base = state.particle_u.numpy().astype(np.float64)
        for bd in args.block:
            for regs, kernel in kernels.items():
                tw = pipe.time_fused(launcher(kernel, bd), args.steps, first_p2g=first_p2g)
                res.setdefault(f"warp{bd}r{regs}", []).append(tw)
                u_warp = state.particle_u.numpy().astype(np.float64)
        runs = ", ".join(f"{k} {1e3 * v[-1]:.4f}" for k, v in res.items() if k != "base")
        print(f"repeat {r}: base {1e3 * tb:.4f} ms, {runs}", flush=True)
    rms = float(np.sqrt((u_base ** 2).sum(1).mean()))
    d = float(np.sqrt(((u_base - u_warp) ** 2).sum(1).mean()))
    print(f"u RMS {rms:.6e}; base vs warp RMS diff {d:.3e} ({d / rms:.2e} relative); "
          f"overrun {int(pipe.overrun.numpy()[0])}")
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
