"""How the order of the particles in memory changes the cost of a rollout.

P2G adds every particle's contribution to its 27 grid nodes with float atomics. Threads that
run together (a GPU warp: 32 consecutive particle indices) and hit the same nodes serialize
on those atomics. The paper-scale assets put most particles on a thin shell of Gaussian
centres, many to a cell, so the order decides how often that happens. Three orders of the
same particles, the Gaussian-associated ones first as always (the permutation acts within
the Gaussian-associated rows and within the fill rows):

- ``asset``: as the asset is built (the solver's order today);
- ``random``: a seeded random permutation (warp-mates rarely share a node);
- ``cell``: sorted by grid cell (warp-mates mostly share nodes).

One Probe-A rollout at theta = (1, 1) per order (simulated in that order:
``particle_order="asset"``; rollouts on a GPU use the cell order by default), after a warm-up
rollout that loads the kernels; median of ``--repeats``.

    python3 benchmarks/particle_order_bench.py --object pillow --profile paper --device cuda:0
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np


def reorder(ps, order: str, n_grid: int, grid_lim: float, *, seed: int = 0):
    """``ps`` with its rows permuted within the Gaussian-associated block and within the fill."""
    n, g = len(ps.positions), ps.n_gs
    if order == "asset":
        return ps
    if order == "random":
        rng = np.random.default_rng(seed)
        perm = np.concatenate([rng.permutation(g), g + rng.permutation(n - g)])
    elif order == "cell":
        cell = np.floor(ps.positions / (grid_lim / n_grid)).astype(np.int64)
        key = (cell[:, 0] * n_grid + cell[:, 1]) * n_grid + cell[:, 2]
        perm = np.concatenate([np.argsort(key[:g], kind="stable"), g + np.argsort(key[g:], kind="stable")])
    else:
        raise ValueError(order)
    return dataclasses.replace(ps, positions=ps.positions[perm],
                               volumes=None if ps.volumes is None else ps.volumes[perm],
                               gaussian_index=ps.gaussian_index[perm[:g]], region=ps.region[perm])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--orders", nargs="+", default=["asset", "random", "cell"])
    args = ap.parse_args()

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import run_rollout

    contract = load_contract(args.object, args.profile)
    ps = build_asset(contract).particles
    probe = contract.roles["calibration"]
    sim = contract.sim
    print(f"{args.object} {args.profile}: {ps.n_gs} GS + {len(ps.positions) - ps.n_gs} fill particles, n_grid {sim.n_grid}, "
          f"dt {sim.dt}, device {args.device}", flush=True)
    run_rollout(contract, (1.0, 1.0), probe, particles=ps, device=args.device)  # kernels loaded
    rows = []
    for order in args.orders:
        p = reorder(ps, order, sim.n_grid, sim.grid_lim)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ro = run_rollout(contract, (1.0, 1.0), probe, particles=p, device=args.device, particle_order="asset")
            times.append(time.perf_counter() - t0)
        rms = float(np.sqrt(np.mean((ro.positions[-1, : ps.n_gs] - ro.positions[0, : ps.n_gs]) ** 2)))
        rows.append((order, statistics.median(times), ro.meta["stats"]["steps"], rms))
        print(rows[-1], flush=True)
    print("| order | s per rollout | ms per substep | rms final displacement of the GS particles |")
    print("|---|---:|---:|---:|")
    for order, s, steps, rms in rows:
        print(f"| {order} | {s:.2f} | {1e3 * s / steps:.3f} | {rms:.4e} |")


if __name__ == "__main__":
    main()
