"""Simulator throughput: particle-substeps per second and seconds per 6000-substep rollout.

Body: a block of jelly (E = 1e4 Pa, nu = 0.3, rho = 2000 kg/m^3) with 8 particles per cell
(``--ppc``: 8, 27, 64, ...),
centred in the [0, 2]^3 domain, knocked by a one-step global probe (as the Pillow contract),
dt = 1e-4 s, with the contracts' affine-FLIP transfer (``--transfer apic`` for the paper's,
``both`` for the two in one run; ``--p2g`` the P2G variants, ``auto`` the solver's choice by
its cell crowding; ``--order cell`` holds the particles sorted by stencil base cell, as a GPU
rollout does, instead of the lattice's order). Each case runs ``--steps`` substeps after a warm-up and reports the median of
``--repeats`` timings. ``--cold`` measures the cold kernel compile in an empty cache.

    python3 benchmarks/sim_bench.py --device cpu
    python3 benchmarks/sim_bench.py --device cuda:0 --cases 100000:100 700000:100
    python3 benchmarks/sim_bench.py --device cuda:0 --cases 681472:100 --ppc 8 27 64 --p2g scatter cells auto
    python3 benchmarks/sim_bench.py --device cuda:0 --cases 681472:100 --order lattice cell --p2g scatter cells
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np


def block(n_particles: int, n_grid: int, grid_lim: float = 2.0, ppc: int = 8) -> np.ndarray:
    dx = grid_lim / n_grid
    per_axis = round(ppc ** (1 / 3))
    cells = max(1, round((n_particles / ppc) ** (1 / 3)))
    if cells > n_grid - 8:
        raise SystemExit(f"{n_particles} particles at {ppc} per cell do not fit n_grid {n_grid}")
    h = dx / per_axis
    side = cells * dx
    axis = (grid_lim - side) / 2 + h * (np.arange(cells * per_axis) + 0.5)
    X = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return X.astype(np.float32)


def run_case(n_particles: int, n_grid: int, steps: int, repeats: int, device: str, *, transfer: str = "affine_flip",
             graph: bool | str = "auto", p2g: str = "auto", ppc: int = 8, order: str = "lattice",
             g2p_sums: str | None = None, polar_update: str | None = None, deformation_storage: str = "auto",
             window_atomics: str | None = None) -> dict:
    import warp as wp

    from knockgs_core.sim import MPMSolver, Probe, SimParams, build_model, make_state

    X = block(n_particles, n_grid, ppc=ppc)
    if order == "cell":  # by stencil base cell, x-major (knockgs_core.rollout.cell_order)
        base = np.floor(X.astype(np.float64) / (2.0 / n_grid) - 0.5).astype(np.int64)
        X = X[np.lexsort((base[:, 2], base[:, 1], base[:, 0]))]
    params = SimParams(n_grid=n_grid, dt=1e-4, transfer=transfer)
    model = build_model(X, E=1e4, nu=0.3, rho=2000.0, params=params, probe=Probe("standard_x", (-0.18, 0.0, 0.0)), device=device)
    model.deformation_storage = deformation_storage
    state = make_state(model, X)
    reproducible = p2g == "cells-fixed"  # MPMSolver(deterministic=True): no float atomics on the grid
    solver = MPMSolver(model, graph=graph, p2g="cells" if reproducible else p2g, deterministic=reproducible,
                       g2p_sums=g2p_sums, polar_update=polar_update, window_atomics=None if reproducible else window_atomics)
    solver.check(state)
    for _ in range(20):  # warm-up (kernel load, caches)
        solver.step(state)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for s in range(steps):
            solver.step(state)
            if state.step % params.guard_every == 0:
                solver.check(state)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    rate = len(X) * steps / med
    return {
        "particles": len(X),
        "n_grid": n_grid,
        "transfer": transfer,
        "graph": solver.graph,
        "ppc": ppc,
        "p2g": solver.p2g,
        "p2g_asked": p2g,
        "crowding": solver.crowding,
        "order": order,
        "g2p_sums": solver.g2p_sums,
        "polar_update": solver.polar_update,
        "window_atomics": solver.window_atomics,
        "deformation_storage": deformation_storage,
        "F_array": f"{state.particle_F.dtype.__name__}{tuple(state.particle_F.shape)}",
        "steps": steps,
        "median_s": med,
        "particle_substeps_per_s": rate,
        "s_per_6000_substeps": 6000 * med / steps,
        "ms_per_substep": 1000 * med / steps,
    }


def cold_compile_seconds() -> float:
    """Seconds to import, initialise and compile the solver module in an empty kernel cache."""
    code = (
        "import time, numpy as np; t0 = time.perf_counter();"
        "import warp as wp; wp.config.kernel_cache_dir = __import__('os').environ['WC'];"
        "from knockgs_core.sim import SimParams, build_model, make_state, MPMSolver;"
        "X = np.full((8, 3), 1.0, np.float32) + np.random.default_rng(0).uniform(0, .05, (8, 3)).astype(np.float32);"
        "m = build_model(X, E=1e4, nu=.3, rho=1e3, params=SimParams(n_grid=32, dt=1e-4)); s = make_state(m, X);"
        "sv = MPMSolver(m); sv.check(s); sv.step(s); print(time.perf_counter() - t0)"
    )
    with tempfile.TemporaryDirectory() as d:
        out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "WC": d}, capture_output=True, text=True,
                             check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="*", help="PARTICLES:N_GRID",
                    default=["5000:32", "5000:64", "5000:100", "20000:32", "20000:64", "100000:64", "100000:100"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--transfer", choices=["affine_flip", "apic", "both"], default="affine_flip")
    ap.add_argument("--graph", choices=["auto", "off", "both"], default="auto",
                    help="substeps as CUDA graphs (auto: on a CUDA device); both: each case with and without")
    ap.add_argument("--p2g", nargs="+", choices=["auto", "scatter", "cells", "cells-fixed"],
                    default=["auto"], help="P2G variants (cells-fixed: MPMSolver(deterministic=True), the fixed-point "
                                           "sums)")
    ap.add_argument("--order", nargs="+", choices=["lattice", "cell"], default=["lattice"],
                    help="the particles' order: the lattice's, or sorted by stencil base cell")
    ap.add_argument("--ppc", nargs="+", type=int, default=[8], help="particles per cell of the block (cubes: 8, 27, 64)")
    ap.add_argument("--g2p-sums", nargs="+", choices=["auto", "nodes", "lines"], default=[None],
                    help="how G2P sums its stencil (SolverConfig.g2p_sums; default: the solver's), each measured")
    ap.add_argument("--polar-update", nargs="+", choices=["auto", "axis_angle", "rational"], default=[None],
                    help="how the polar iterations rotate (SolverConfig.polar_update; default: the solver's), each measured")
    ap.add_argument("--deformation-storage", nargs="+", choices=["auto", "float64", "displacement"], default=["auto"],
                    help="how the states store F (Model.deformation_storage; auto: the displacement gradient in "
                         "float32 on a GPU, F in float64 on the CPU), each measured")
    ap.add_argument("--window-atomics", nargs="+", choices=["auto", "scalar", "vector"], default=[None],
                    help="how the window sums reach the nodes (SolverConfig.window_atomics; default: the solver's), each "
                         "measured")
    ap.add_argument("--cold", action="store_true", help="also measure a cold compile")
    ap.add_argument("--json", help="write results here")
    args = ap.parse_args()
    rows = []
    print(f"# device {args.device}, {platform.processor() or platform.machine()}, python {platform.python_version()}")
    transfers = ["affine_flip", "apic"] if args.transfer == "both" else [args.transfer]
    graphs = {"auto": ["auto"], "off": [False], "both": [False, "auto"]}[args.graph]
    print("| particles | per cell | order | n_grid | transfer | graph | P2G | particle-substeps/s "
          "| G2P sums | polar update | F stored | window atomics | ms/substep | s per 6000-substep rollout |")
    print("|---:|---:|---|---:|---|---|---|---:|---|---|---|---|---:|---:|")
    for case in args.cases:
        n, g = (int(v) for v in case.split(":"))
        for ppc in args.ppc:
            for transfer in transfers:
                for graph in graphs:
                    for order, p2g, g2p, pu, ds, wa in (
                            (o, v, q, u, d, a) for o in args.order for v in args.p2g for q in args.g2p_sums
                            for u in args.polar_update for d in args.deformation_storage for a in args.window_atomics):
                        r = run_case(n, g, args.steps, args.repeats, args.device, transfer=transfer, graph=graph, p2g=p2g,
                                     ppc=ppc, order=order, g2p_sums=g2p, polar_update=pu, deformation_storage=ds,
                                     window_atomics=wa)
                        rows.append(r)
                        crowd = "" if r["crowding"] is None else f" (crowding {r['crowding']:.1f})"
                        print(f"| {r['particles']:,} | {ppc} | {order} | {g} | {transfer} | {'on' if r['graph'] else 'off'} | "
                              f"{p2g}: {r['p2g']}{crowd} | "
                              f"{r['particle_substeps_per_s']:.3g} | {r['g2p_sums']} | {r['polar_update']} | "
                              f"{r['F_array']} | {r['window_atomics']} | {r['ms_per_substep']:.3f} | "
                              f"{r['s_per_6000_substeps']:.2f} |", flush=True)
    out = {"device": args.device, "rows": rows}
    if args.cold:
        out["cold_compile_s"] = cold_compile_seconds()
        print(f"cold compile (import + init + build + first step, empty cache): {out['cold_compile_s']:.1f} s")
    if args.json:
        from knockgs_core.io import write_json

        write_json(args.json, out, indent=1)


if __name__ == "__main__":
    main()
