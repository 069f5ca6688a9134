"""Where a substep's GPU time goes: Warp's per-kernel CUDA timing over a run of substeps.

Builds the object's asset and one Probe-A model at theta = (1, 1), runs ``--warm``
substeps (kernels loaded, the probe applied, the active box settled), then times
``--steps`` substeps kernel by kernel (``wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)``)
and prints each kernel's share. A variant ``cells+graph`` replays each substep as a captured
CUDA graph (``MPMSolver(graph=True)``): its kernels are not timed one by one, only the wall.

The particles are held in a GPU rollout's order (``--order cell``: sorted by stencil base
cell within the Gaussian-associated rows and within the fill, ``knockgs_core.rollout.cell_order``)
or in the asset's (``--order asset``).

    python3 benchmarks/kernel_profile.py --object pillow --profile paper --device cuda:0 --p2g cells cells+graph scatter
    python3 benchmarks/kernel_profile.py --object pillow --device cuda:0 --p2g cells cells+graph --resort 1 10
    python3 benchmarks/kernel_profile.py --object pillow --device cuda:0 --p2g cells+graph --fuse off on
    python3 benchmarks/kernel_profile.py --object pillow --device cuda:0 --p2g cells+graph --particles OUT/pillow.npz
    python3 benchmarks/kernel_profile.py --object pillow --device cuda:0 --p2g cells+graph --deterministic off fixed
"""

from __future__ import annotations

import argparse
import hashlib
import time
from collections import defaultdict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--warm", type=int, default=300)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--p2g", nargs="+", default=["scatter", "cells", "cells+graph"],
                    help="P2G variants of MPMSolver to profile (+graph: substeps replayed as CUDA graphs)")
    ap.add_argument("--order", choices=["cell", "asset"], default="cell")
    ap.add_argument("--particles", help="the object's particles .npz: read where it exists, else built and written "
                                        "there (processes comparing code versions then share one asset)")
    ap.add_argument("--chunk", type=int, nargs="+", default=[32],
                    help="sorted particles a window of the P2G by cells (SolverConfig.cell_chunk), each profiled")
    ap.add_argument("--fuse", nargs="+", choices=["auto", "on", "off"], default=["auto"],
                    help="G2P fused with the next substep's per-particle P2G half (MPMSolver(fuse=...); on: "
                         "the P2G by cells only), each profiled")
    ap.add_argument("--resort", type=int, nargs="+", default=[10],
                    help="intervals of the P2G by cells' sort in substeps (SolverConfig.resort_every), each profiled")
    ap.add_argument("--deterministic", nargs="+", choices=["off", "fixed"], default=["off"],
                    help="the bitwise-reproducible P2G (MPMSolver(deterministic=...); fixed: the windows' sums added "
                         "as fixed-point integers), each profiled; list one twice to compare the runs' bits (MD5 of u)")
    ap.add_argument("--fast-math", action="store_true",
                    help="compile the solver's kernels with fast math (approximate division, square root, sine and "
                         "cosine; denormals flushed): a measurement only, the solver never does")
    ap.add_argument("--block-dim", type=int, default=0,
                    help="threads per block of the solver's launches (Warp's module option; 0: Warp's default)")
    ap.add_argument("--max-registers", type=int, default=0,
                    help="cap on the registers per thread of the unfused particle kernels (CUDA __maxnreg__; 0: "
                         "the solver's, _kernels.CUDA_MAX_REGISTERS on its heavy kernels; the fused g2p_prepare, a "
                         "kernel per transfer, keeps the solver's)")
    ap.add_argument("--polar-step", type=float, nargs="+", default=[None],
                    help="the polar iterations' step (MPMSolver(polar_step=...); default: the solver's, 1.5 on a GPU), "
                         "each profiled")
    ap.add_argument("--guard", action="store_true",
                    help="run the guard every guard_every substeps in the timed loop, as a rollout does")
    ap.add_argument("--polar-update", nargs="+", choices=["auto", "axis_angle", "rational"], default=["auto"],
                    help="how the polar iterations rotate (MPMSolver(polar_update=...); auto: rational on a GPU), "
                         "each profiled")
    ap.add_argument("--g2p-sums", nargs="+", choices=["auto", "nodes", "lines"], default=["auto"],
                    help="how G2P sums its stencil (MPMSolver(g2p_sums=...); auto: lines on a GPU), each profiled")
    ap.add_argument("--deformation-storage", nargs="+", choices=["auto", "float64", "displacement"], default=["auto"],
                    help="how the states store F (Model.deformation_storage; auto: the displacement gradient in "
                         "float32 on a GPU), each profiled")
    ap.add_argument("--window-atomics", nargs="+", choices=["auto", "scalar", "vector"], default=["auto"],
                    help="how the window sums reach the nodes (MPMSolver(window_atomics=...); auto: vector on a GPU "
                         "where P2G sums by windows), each profiled")
    args = ap.parse_args()

    import warp as wp

    from knockgs_core.sim import _kernels

    options = {}
    if args.fast_math:
        options["fast_math"] = True
    if args.block_dim:
        options["block_dim"] = args.block_dim
    if options:
        wp.set_module_options(options, module=_kernels)
    particle_kernels = ("p2g_prepare", "g2p")
    if args.max_registers:  # the same kernels with the cap, in the solver's Warp module (the solver looks them up by name)
        for name in particle_kernels:
            kernel = wp.kernel(getattr(_kernels, name).func, cuda_max_registers=args.max_registers, module=_kernels.MODULE)
            setattr(_kernels, name, kernel)

    from _object_model import object_particles, probe_a_model

    from knockgs_core.contract import load_contract
    from knockgs_core.sim import MPMSolver, make_state

    contract = load_contract(args.object, args.profile)
    ps = object_particles(contract, args.particles, order=args.order)
    model = probe_a_model(contract, ps, args.device)
    runs = [(v, r, k, f, d, ps_, pu, g, ds, wa) for v in args.p2g for r in args.resort for k in args.chunk
            for f in args.fuse for d in args.deterministic for ps_ in args.polar_step for pu in args.polar_update
            for g in args.g2p_sums for ds in args.deformation_storage for wa in args.window_atomics]
    for variant, resort, chunk, fuse, det, polar_step, polar_update, g2p_sums, storage, atomics in runs:
        model.deformation_storage = storage
        state = make_state(model, ps.positions)
        p2g, graph = variant.split("+")[0], variant.endswith("+graph")
        fuse = {"auto": "auto", "on": True, "off": False}[fuse]
        if fuse is True and p2g != "cells":
            continue
        if det == "fixed" and p2g != "cells":  # the fixed-point sums sum by cells
            continue
        solver = MPMSolver(model, p2g=p2g, graph=graph, fuse=fuse, resort_every=resort, cell_chunk=chunk,
                           deterministic=det != "off", polar_update=polar_update, g2p_sums=g2p_sums, window_atomics=atomics,
                           **({} if polar_step is None else {"polar_step": polar_step}))
        solver.check(state)
        for _ in range(args.warm):
            solver.step(state)
            if state.step % contract.sim.guard_every == 0:
                solver.check(state)
        wp.synchronize_device(args.device)
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            solver.step(state)
            if args.guard and state.step % contract.sim.guard_every == 0:
                solver.check(state)
        wp.synchronize_device(args.device)
        wall = time.perf_counter() - t0
        results = wp.timing_end()
        total = defaultdict(float)
        count = defaultdict(int)
        for r in results:
            total[r.name] += r.elapsed
            count[r.name] += 1
        all_ms = sum(total.values())
        print(f"{args.object} {args.profile}, P2G {variant} ({args.order} order, sort every "
              f"{resort} substeps, windows of {chunk}, "
              f"G2P fused with the next P2G half: {solver.fuse}, "
              f"reproducible: {solver.deterministic} ({solver.reproducible_sums}), "
              f"polar step {getattr(solver, 'polar_step', 1.0)} "
              f"({getattr(solver, 'polar_update', 'axis_angle')}), "
              f"G2P sums by {getattr(solver, 'g2p_sums', 'nodes')}, "
              f"window atomics {getattr(solver, 'window_atomics', 'scalar')}, "
              f"F stored as {state.particle_F.dtype.__name__}{tuple(state.particle_F.shape)}, "
              f"module options {options or 'default'}, guard in the loop: {args.guard}, "
              f"register cap {args.max_registers or 'none'}): "
              f"{len(ps.positions)} particles, n_grid {contract.sim.n_grid}, "
              f"active box {[h - lo for lo, h in zip(solver._lo, solver._hi)]}, {args.steps} substeps, "
              f"wall {1e3 * wall / args.steps:.4f} ms per substep")
        print("| kernel | launches | ms per substep | share |")
        print("|---|---:|---:|---:|")
        for name, ms in sorted(total.items(), key=lambda kv: -kv[1]):
            print(f"| {name} | {count[name]} | {ms / args.steps:.4f} | {100 * ms / max(all_ms, 1e-12):.1f} % |")
        print(f"| all | {sum(count.values())} | {all_ms / args.steps:.4f} | 100 % |")
        if wp.get_device(args.device).is_cuda:
            props = []
            kernels = {name: getattr(_kernels, name) for name in particle_kernels}
            kernels.update({k.key: k for k in map(_kernels.g2p_prepare, (0, 1))})  # one a transfer
            for name, kernel in kernels.items():
                try:
                    q = wp.get_cuda_kernel_properties(kernel, device=args.device)
                except RuntimeError:  # not loaded in this variant
                    continue
                props.append(f"{name} {q['register_count']} registers, {q['local_memory_size']} B local")
            print("kernels: " + "; ".join(props))
        u32 = state.particle_u.numpy()
        u = u32.astype("float64")
        print(f"RMS displacement after {state.step} substeps: {float((u ** 2).sum(axis=1).mean() ** 0.5):.9e} m "
              "(the same response under every variant, to float rounding); MD5 of u "
              f"{hashlib.md5(u32.tobytes()).hexdigest()}")



if __name__ == "__main__":
    main()
