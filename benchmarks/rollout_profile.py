"""Where one rollout's wall time goes: host work, the guard's read-backs (where the host waits
for the device), exports and launch recording, with cProfile's top entries.

Builds the object's asset, runs one warm-up rollout (kernels loaded), then profiles Probe-A
rollouts at theta = (1, 1) without and with the deformation-gradient export, and times
writing each.

    python3 benchmarks/rollout_profile.py --object pillow --profile paper --device cuda:0
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import tempfile
import time
from collections import defaultdict
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--top", type=int, default=15)
    args = ap.parse_args()

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import run_rollout, write_rollout
    from knockgs_core.sim import _simulate, _solver

    seconds, calls = defaultdict(float), defaultdict(int)

    def timed(owner, name):
        inner = getattr(owner, name)

        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return inner(*a, **k)
            finally:
                seconds[name] += time.perf_counter() - t
                calls[name] += 1

        setattr(owner, name, wrapper)

    for name in ("step", "check", "_record"):
        timed(_solver.MPMSolver, name)
    timed(_simulate._Exporter, "export")

    contract = load_contract(args.object, args.profile)
    t = time.perf_counter()
    ps = build_asset(contract).particles
    print(f"asset: {ps.n_gs + ps.n_fill} particles in {time.perf_counter() - t:.1f} s")
    probe = contract.roles["calibration"]
    t = time.perf_counter()
    run_rollout(contract, (1.0, 1.0), probe, particles=ps, device=args.device)
    print(f"warm-up rollout: {time.perf_counter() - t:.2f} s")
    with tempfile.TemporaryDirectory() as out:
        for export_F in (False, True):
            seconds.clear()
            calls.clear()
            prof = cProfile.Profile()
            t = time.perf_counter()
            prof.enable()
            ro = run_rollout(contract, (1.0, 1.0), probe, particles=ps, device=args.device, export_F=export_F)
            prof.disable()
            wall = time.perf_counter() - t
            t = time.perf_counter()
            write_rollout(Path(out) / "rollout.parquet", ro)
            write_s = time.perf_counter() - t
            print(f"\nrollout ({probe}, F exported: {export_F}): {wall:.3f} s, written in {write_s:.3f} s")
            print("| solver method | calls | s |")
            print("|---|---:|---:|")
            for name in ("step", "check", "export", "_record"):
                print(f"| {name} | {calls[name]} | {seconds[name]:.3f} |")
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(args.top)
            print(text.getvalue())


if __name__ == "__main__":
    main()
