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
from pathlib import Path


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
    from knockgs_core.assets import build_asset, load_particles, save_particles
    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import _permuted, cell_order
    from knockgs_core.sim import MPMSolver, build_model, make_state

    c = load_contract(args.object, args.profile)
    if args.particles and Path(args.particles).exists():
        ps = load_particles(args.particles, contract=c)
    else:
        ps = build_asset(c).particles
        if args.particles:
            save_particles(ps, args.particles, contract=c)
    ps = _permuted(ps, cell_order(ps, n_grid=c.sim.n_grid, grid_lim=c.sim.grid_lim))
    probe = c.resolve_probes(ps)[c.roles["calibration"]]
    E, nu, rho = c.particle_materials(ps, (1.0, 1.0))
    ref = getattr(c, "probe_reference_particles", None)
    model = build_model(ps.positions, E=E, nu=nu, rho=rho, params=c.sim, volumes=ps.volumes, probe=probe,
                        probe_force_scale=float(ref) / len(ps.positions) if ref else 1.0, device=args.device)
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
