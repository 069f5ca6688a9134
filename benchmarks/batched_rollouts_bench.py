"""Candidate rollouts of one object simulated together on one GPU, against one at a time.

:func:`knockgs_core.rollout.run_rollouts` steps several rollouts in lockstep, each on its own
CUDA stream, so the GPU overlaps their kernels (P2G's float atomics pile up on the nodes of a
densely sampled shell; on separate grids they do not wait for each other). Here: the first
``--count`` candidates of ``config/candidates.csv`` under the calibration probe (Probe A), once
one after the other (:func:`run_rollout`) and once in batches of ``--batch``; the same
positions up to the GPU's float-atomic rounding (the largest difference is printed).

    python3 benchmarks/batched_rollouts_bench.py --object pillow --profile paper --device cuda:0 --count 6 --batch 3 6
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--count", type=int, default=6)
    ap.add_argument("--batch", type=int, nargs="+", default=[3, 6])
    ap.add_argument("--particles", help="the object's particles .npz: read where it exists, else built and written "
                                        "there")
    ap.add_argument("--export-F", action="store_true",
                    help="export the Gaussian-associated particles' deformation gradients too, as library jobs do")
    args = ap.parse_args()

    from _object_model import object_particles

    from knockgs_core.contract import load_candidates, load_contract
    from knockgs_core.rollout import run_rollout, run_rollouts

    contract = load_contract(args.object, args.profile)
    ps = object_particles(contract, args.particles, order="asset")
    probe = contract.roles["calibration"]
    cand = load_candidates()
    thetas = [(float(e), float(r)) for e, r in zip(cand["E_scale"], cand["density_scale"])][: args.count]
    print(f"{args.object} {args.profile}: {len(ps.positions)} particles, {len(thetas)} candidates, device {args.device}",
          flush=True)
    F = args.export_F
    run_rollout(contract, thetas[0], probe, particles=ps, device=args.device, export_F=F)  # kernels loaded

    t0 = time.perf_counter()
    alone = [run_rollout(contract, th, probe, particles=ps, device=args.device, export_F=F).positions for th in thetas]
    serial = time.perf_counter() - t0
    rows = [("one at a time", 1, serial, 0.0)]
    for b in args.batch:
        t0 = time.perf_counter()
        together = []
        for k in range(0, len(thetas), b):
            together += [ro.positions for ro in run_rollouts(contract, [(th, probe) for th in thetas[k:k + b]], particles=ps,
                                                               device=args.device, export_F=F)]
        wall = time.perf_counter() - t0
        diff = max(float(np.abs(a - t).max()) for a, t in zip(alone, together))
        rows.append((f"batches of {b}", b, wall, diff))
        print(rows[-1], flush=True)
    print(f"| mode | batch | s for {len(thetas)} rollouts | s per rollout | speed-up | max abs position difference [m] |")
    print("|---|---:|---:|---:|---:|---:|")
    for mode, b, wall, diff in rows:
        print(f"| {mode} | {b} | {wall:.1f} | {wall / len(thetas):.2f} | {serial / wall:.2f}x | {diff:.2e} |")


if __name__ == "__main__":
    main()
