"""The Probe-A convergence study at a resolution profile too large for the CPU, on a GPU.

Runs :func:`knockgs_core.experiments.convergence_study` (the same code as the workflow's
``convergence`` rule) for each named object at ``--profile`` on ``--device`` and writes
``convergence_{object}.csv|md`` and a JSON of wall times to ``--out``. ``--refinements``
picks the studies (default: time only, ``dt -> dt/2 -> dt/4``); ``--dt-levels 4`` adds a
fourth level (dt/8) and a second order estimate from levels 2-4.

    python3 benchmarks/convergence_gpu.py --objects ficus vasedeck pillow --profile paper \\
        --device cuda:0 --out OUT
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="+", default=["ficus", "vasedeck", "pillow"])
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--refinements", nargs="+", default=["dt"])
    ap.add_argument("--theta", nargs=2, type=float, default=[1.15, 0.75])
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import convergence_note, convergence_study
    from knockgs_core.reporting import write_table

    args.out.mkdir(parents=True, exist_ok=True)
    timing = {}
    for name in args.objects:
        t0 = time.perf_counter()
        contract = load_contract(name, args.profile)
        particles = build_asset(contract).particles
        t_asset = time.perf_counter() - t0
        t0 = time.perf_counter()
        table = convergence_study(contract, particles, theta=tuple(args.theta), refinements=args.refinements,
                                  device=args.device, log=lambda m: print(m, flush=True))
        timing[name] = {"asset_s": t_asset, "study_s": time.perf_counter() - t0,
                        "particles": int(len(particles.positions))}
        write_table(table, args.out / f"convergence_{name}.csv", args.out / f"convergence_{name}.md",
                    title=f"Probe-A convergence: {name} ({args.profile}, {args.device})", note=convergence_note(table))
        cols = ["refinement", "level_1", "level_2", "level_3", "change_1_2", "change_2_3", "observed_order",
                "richardson_error_pct"]
        print(table[cols].to_string(index=False), flush=True)
        print(json.dumps(timing[name]), flush=True)
    (args.out / "timing.json").write_text(json.dumps(timing, indent=2, default=float))
    np.set_printoptions(precision=4)


if __name__ == "__main__":
    main()
