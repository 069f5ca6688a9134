"""Does the finite-element reference converge? One body, meshed ever finer (CPU, minutes a level).

The body is an object's particle set built at ``--body-n-grid`` (the floor study's reference
construction: ``at_resolution``, the fill refined with the grid). It is held fixed while the
mesh is refined: the FEM (P2, Newmark; the floor block's settings) runs on meshes of the cells
of ``--levels``, either the voxels its particles occupy (``--fem-body voxel``: a staircase
boundary, each cell carrying its particles' volume) or its fill's surface meshed to it
(``--fem-body level_set``). Each level is compared with the finest: the Probe-A trajectory gap
(RMSE over the Probe-A record, % of the finest's RMS displacement) and the first-mode period over
the floor block's longer record; the observed order of the gaps, and the finest level's own gap
extrapolated at that order.

    python3 benchmarks/reference_convergence.py --object vasedeck --profile config --solid \
        --body-n-grid 96 --levels 32 48 64 --fem-body level_set --jobs 3 --cache fem_cache --out ref_conv

writes ``reference_{object}_{fem_body}.csv`` and ``.md`` under ``--out``; the levels run in
``--jobs`` processes (each solve is one core's), kept in ``--cache`` (the floor study's
finite-element cache: the same runs are read back there).
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from _floor_object import add_object_arguments, floor_object


def _setup(args):
    from knockgs_core.assets import build_asset
    from knockgs_core.experiments import at_resolution
    from knockgs_core.experiments._floor import _with_record

    contract, settings = floor_object(args)
    gs = build_asset(contract).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)
    probe = contract.roles["calibration"]
    n_long = (int(contract.probes[probe].export.n_frames) - 1) * int(settings.record_factor) + 1
    body = at_resolution(contract, args.body_n_grid)
    return settings, _with_record(body, probe, n_long), build_asset(body).particles, points, probe


def _level(args, n):
    from knockgs_core.experiments._floor import _fem_run
    from knockgs_core.fem import FemWorld

    settings, body, particles, points, probe = _setup(args)
    world = FemWorld(degree=settings.fem_degree, steps_per_frame=settings.fem_steps_per_frame, n_grid=int(n),
                     body=args.fem_body, body_resolution=args.body_resolution, solver=args.solver)
    return _fem_run(body, particles, points, world, (1.0, 1.0), probe, cache=args.cache)


def main() -> None:
    from knockgs_core.experiments import probe_period
    from knockgs_core.io import write_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_object_arguments(ap, default_object="vasedeck")
    ap.add_argument("--body-n-grid", type=int, required=True)
    ap.add_argument("--levels", type=int, nargs="+", required=True, help="mesh grids, increasing")
    ap.add_argument("--fem-body", default="level_set", choices=("voxel", "level_set"))
    ap.add_argument("--solver", default="auto", choices=("auto", "direct", "cg"),
                    help="Newmark's linear solver (direct: a factorization at every size, memory allowing)")
    ap.add_argument("--body-resolution", type=int, default=None,
                    help="the fill grid the level-set body is measured on (default: the construction's fill)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    levels = sorted(set(args.levels))
    settings, body, particles, points, probe = _setup(args)
    pr = body.probes[probe]
    n_rec = int(pr.export.n_frames) // int(settings.record_factor) + 1
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        runs = dict(zip(levels, pool.map(_level, [args] * len(levels), levels)))
    finest = runs[levels[-1]]["u"]
    times = np.arange(finest.shape[0]) * float(pr.export.frame_dt)
    scale = np.linalg.norm(finest[:n_rec])
    rows = []
    for n in levels:
        r = runs[n]
        rows.append({"n_grid": n, "dx_m": body.sim.grid_lim / n, "dofs": r["dofs"], "volume_m3": r["volume"],
                     "gap_pct": 100.0 * np.linalg.norm(r["u"][:n_rec] - finest[:n_rec]) / scale,
                     "period_s": probe_period(times, r["u"], pr.force), "cost_s": r["cost"], "kept": r["cached"]})
    order = float("nan")
    if len(levels) >= 3:
        (g1, g2) = rows[-3]["gap_pct"], rows[-2]["gap_pct"]
        h = [1.0 / n for n in levels[-3:]]
        f = lambda p: (h[0] ** p - h[2] ** p) / (h[1] ** p - h[2] ** p) - g1 / g2  # noqa: E731
        lo, hi = 0.05, 8.0
        if f(lo) * f(hi) < 0:
            for _ in range(100):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if f(lo) * f(mid) > 0 else (lo, mid)
            order = 0.5 * (lo + hi)
    own = rows[-2]["gap_pct"] / ((levels[-1] / levels[-2]) ** order - 1) if np.isfinite(order) else float("nan")
    import pandas as pd

    table = pd.DataFrame(rows)
    stem = f"reference_{args.object}_{args.fem_body}" + (f"_b{args.body_resolution}" if args.body_resolution else "")
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / f"{stem}.csv", table.to_csv(index=False))
    note = (f"{args.object} ({args.profile}{', solid' if args.solid else ''}), body built at n_grid {args.body_n_grid}, "
            f"{args.fem_body} meshes {levels}: observed order of the gaps {order:.2f}; the finest's own gap "
            f"~{own:.1f} % at that order. {time.perf_counter() - t0:.0f} s.\n\n"
            f"{table.to_markdown(index=False, floatfmt='.4g')}\n")
    write_text(args.out / f"{stem}.md", note)
    print(note)


if __name__ == "__main__":
    main()
