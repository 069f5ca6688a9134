"""Substeps of a paper-scale object with the solver's GPU defaults, no graphs, for a kernel
profiler to attach to (Nsight Compute: each kernel launched once a substep).

    ncu --clock-control none -k regex:"p2g_windows|g2p_prepare" --launch-skip 60 --launch-count 2 --set full \\
        -o OUT/prof python3 benchmarks/profiler_substeps.py --object pillow --steps 70 --particles OUT/pillow.npz
    ncu --import OUT/prof.ncu-rep --page details

``--lineinfo`` compiles the kernels with line information (source-level counters:
``ncu --import OUT/prof.ncu-rep --page source --csv --print-source cuda,sass``).
"""

from __future__ import annotations

import argparse

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--steps", type=int, default=70)
    ap.add_argument("--particles", help="the object's particles .npz: read where it exists, else built and written there")
    ap.add_argument("--lineinfo", action="store_true", help="compile the kernels with line information")
    args = ap.parse_args()

    import warp as wp

    if args.lineinfo:
        wp.config.lineinfo = True
    from _object_model import object_particles, probe_a_model

    from knockgs_core.contract import load_contract
    from knockgs_core.sim import MPMSolver, make_state

    c = load_contract(args.object, args.profile)
    ps = object_particles(c, args.particles)
    model = probe_a_model(c, ps, args.device)
    state = make_state(model, ps.positions)
    solver = MPMSolver(model, graph=False)
    solver.check(state)
    for _ in range(args.steps):
        solver.step(state)
    wp.synchronize_device(args.device)
    print(f"{args.object} {args.profile}: {len(ps.positions)} particles, {state.step} substeps, P2G {solver.p2g} "
          f"(sums by {solver.cell_sums}), fused G2P {solver.fuse}, polar step {solver.polar_step}")


if __name__ == "__main__":
    main()
