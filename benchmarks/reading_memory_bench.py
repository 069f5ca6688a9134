"""Peak memory of the jobs that read paper-scale rollouts on threads, by thread count.

Writes synthetic rollouts at the paper profile's largest size (the Pillow's duration-shift
probe: 121 frames, 695,881 particles, 584,000 of them Gaussian-associated) for ``--targets``
targets, each with its truth and one prediction; then, each in a fresh process, scores them as
the duration table does (:func:`knockgs_core.experiments.evaluate_methods`, two methods sharing
the prediction) and audits them as the non-finite audit does
(:func:`knockgs_core.audits.audit_nonfinite`), with 1, 2, ... threads, and prints each
process's peak resident memory (``VmHWM`` of ``/proc/self/status``: this process's own, where
``ru_maxrss`` would carry over the parent's at the fork; Linux only) and time. The workflow's ``READ_MEM_MB`` for
those rules comes from these numbers.

    python3 benchmarks/reading_memory_bench.py [--targets 4] [--workers 1 2 4] [--frames 121] [--dir DIR]
    python3 benchmarks/reading_memory_bench.py --targets 1 --jobs read table
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _synthetic import sway, swaying_cloud

CHILD = r"""
import json, sys, time
import pandas as pd
from knockgs_core.audits import audit_nonfinite
from knockgs_core.experiments import evaluate_methods
job, folder, workers, n = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
t0 = time.perf_counter()
if job == "evaluate":
    targets = pd.DataFrame({"case_name": [f"t{i}" for i in range(n)], "E_scale": [1.0 + i for i in range(n)],
                            "density_scale": [1.0] * n})
    est = {"predictions": [{"case_name": f"t{i}", "E_scale": 1.0 + i, "density_scale": 2.0} for i in range(n)]}
    where = lambda probe, th: f"{folder}/{'truth' if th[1] == 1.0 else 'pred'}{int(th[0]) - 1}.parquet"
    rows = evaluate_methods({"a": est, "b": est}, targets, where, ["p"], workers=workers)
    assert len(rows["a"]) == n
elif job == "audit":
    assert audit_nonfinite([folder], [], workers=workers)["passed"]
elif job == "read":  # one rollout file, as every reader of rollouts reads it
    from knockgs_core.rollout import read_rollout
    assert read_rollout(f"{folder}/truth0.parquet").positions.size
else:  # "table": Arrow's whole table of the same file, for scale
    import pyarrow.parquet as pq
    assert pq.read_table(f"{folder}/truth0.parquet").num_rows
peak_kb = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
print(json.dumps({"seconds": time.perf_counter() - t0, "peak_gb": peak_kb / 2**20}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--frames", type=int, default=121)
    ap.add_argument("--particles", type=int, default=695_881)
    ap.add_argument("--gs", type=int, default=584_000)
    ap.add_argument("--dir", help="folder for the synthetic rollouts (default: a temporary one)")
    ap.add_argument("--jobs", nargs="+", choices=["evaluate", "audit", "read", "table"], default=["evaluate", "audit"],
                    help="what each fresh process does: score the targets, audit the files, read one file, or read "
                         "one file as Arrow's whole table (read and table take one thread)")
    args = ap.parse_args()
    from knockgs_core.rollout import Rollout, write_rollout

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        rng = np.random.default_rng(0)
        T, N = args.frames, args.particles
        x0, wave = swaying_cloud(rng, T, N)
        meta = {"n_gs": args.gs, "n_fill": N - args.gs, "export_times": list(range(T))}
        t0 = time.perf_counter()
        for i in range(args.targets):
            truth = sway(rng, x0, wave)
            write_rollout(Path(tmp) / f"truth{i}.parquet", Rollout(truth, None, meta))
            pred = truth + np.float32(1e-4) * wave
            write_rollout(Path(tmp) / f"pred{i}.parquet", Rollout(pred, None, meta))
            del truth, pred
        size = sum(p.stat().st_size for p in Path(tmp).glob("*.parquet")) / 2**30
        print(f"{2 * args.targets} rollouts of {T} frames x {N} particles ({size:.1f} GB on disk) written in "
              f"{time.perf_counter() - t0:.0f} s")
        print("| job | threads | peak resident memory [GB] | seconds |")
        print("|---|---:|---:|---:|")
        for job in args.jobs:
            for w in (args.workers if job in ("evaluate", "audit") else [1]):
                out = subprocess.run([sys.executable, "-c", CHILD, job, tmp, str(w), str(args.targets)],
                                     capture_output=True, text=True)
                if out.returncode < 0:  # the kernel's OOM killer, typically
                    print(f"| {job} | {w} | killed (signal {-out.returncode}) | |", flush=True)
                    continue
                if out.returncode != 0:
                    raise SystemExit(out.stderr[-2000:])
                r = json.loads(out.stdout.strip().splitlines()[-1])
                print(f"| {job} | {w} | {r['peak_gb']:.2f} | {r['seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
