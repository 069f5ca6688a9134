"""One object's main table at paper scale on a GPU, timed stage by stage.

Runs the workflow's own rules for one object (asset -> candidate library rollouts ->
descriptors -> frozen estimates -> write-back rollouts under Probe A and each Probe B ->
evaluation -> main table) through Snakemake, so the numbers are those of the workflow, then
collects the time of each job from the rules' benchmark files
(``results/{profile}/benchmarks/``). Writes ``timing.json`` and a copy of the main table to
``--out``; the workflow's own outputs stay under ``results/{profile}/`` (finished jobs are
not re-run: ``--fresh`` re-runs every job of the table).

    python3 benchmarks/paper_gpu.py --object pillow --profile paper --device cuda:0 --out OUT

``--rollouts-only`` times the asset and one rollout per evaluation probe at theta = (1, 1),
with the library calls of the workflow's asset and rollout scripts, then stops.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
CONFIG_FILES = {"ci": "config/ci.yaml", "default": "config/config.yaml", "paper": "config/paper.yaml"}


def rollouts_only(args, out: Path) -> dict:
    """Time the asset build and one rollout per evaluation probe (theta = (1, 1))."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import RolloutStream, run_rollout, write_rollout

    timing: dict = {}
    t0 = time.perf_counter()
    contract = load_contract(args.object, args.profile)
    ps = build_asset(contract).particles
    timing["asset_s"] = time.perf_counter() - t0
    print(f"asset: {ps.n_gs} GS + {ps.n_fill} fill particles in {timing['asset_s']:.1f} s", flush=True)
    rows = []
    for probe in [contract.roles["calibration"]] + list(contract.roles["heldout"]):
        path = out / f"{probe}.parquet"
        stream = RolloutStream(path) if args.stream else None  # the rollout jobs' way: frames written as they come
        t = time.perf_counter()
        ro = run_rollout(contract, (1.0, 1.0), probe, particles=ps, device=args.device, stream=stream)
        t_sim = time.perf_counter() - t
        t = time.perf_counter()
        if stream is not None:
            stream.wait()  # the last frames and the footer
        else:
            write_rollout(path, ro)
        rows.append({"probe": probe, "substeps": ro.meta["stats"]["steps"], "simulate_s": t_sim,
                     "write_s": time.perf_counter() - t, "written": "streamed" if stream else "whole",
                     "particles": ps.n_gs + ps.n_fill,
                     "max_cfl": ro.meta["stats"]["max_cfl"]})
        print(rows[-1], flush=True)
    timing["rollouts"] = rows
    return timing


def stage_times(benchmarks: Path, since: float) -> dict:
    """Jobs and seconds per stage, from the benchmark files the run wrote (``s``: wall time)."""
    stages: dict[str, list[float]] = {}
    for tsv in sorted(benchmarks.rglob("*.tsv")):
        if tsv.stat().st_mtime < since:
            continue  # a job this run did not execute
        parts = tsv.relative_to(benchmarks).parts[:-1]  # e.g. ("rollouts", "pillow", "lib")
        stage = "/".join(parts[:1] + parts[2:])  # the stage without the object: "rollouts/lib"
        stages.setdefault(stage, []).extend(pd.read_csv(tsv, sep="\t")["s"].tolist())
    return {k: {"jobs": len(v), "total_s": float(sum(v)), "median_s": float(pd.Series(v).median())} for k, v in stages.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper", choices=sorted(CONFIG_FILES))
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--cores", type=int, default=4)
    ap.add_argument("--out", required=True)
    ap.add_argument("--fresh", action="store_true", help="re-run every job of the main table (Snakemake --forceall)")
    ap.add_argument("--rollouts-only", action="store_true", help="time the asset and one rollout per evaluation probe, then stop")
    ap.add_argument("--stream", action="store_true",
                    help="with --rollouts-only: write each rollout's frames while it runs (write_s: after the simulation)")
    args = ap.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)

    if args.rollouts_only:
        (out / "timing.json").write_text(json.dumps(rollouts_only(args, out), indent=1))
        return

    table = f"results/{args.profile}/tables/main_{args.object}"
    # targets first: --config takes a list of values and would swallow them
    cmd = [sys.executable, "-m", "snakemake", f"{table}.csv", "--cores", str(args.cores),
           f"--configfile={CONFIG_FILES[args.profile]}", "--resources", "gpu=1", *(["--forceall"] if args.fresh else []),
           "--config", f"objects=[{args.object}]", f"device={args.device}"]
    t0 = time.time()
    subprocess.run(cmd, cwd=ROOT, check=True)
    timing = {"command": " ".join(cmd[1:]), "wall_s": time.time() - t0,
              "stages": stage_times(ROOT / f"results/{args.profile}/benchmarks", since=t0)}
    for ext in ("csv", "md"):
        shutil.copy(ROOT / f"{table}.{ext}", out / f"main_{args.object}_{args.profile}.{ext}")
    (out / "timing.json").write_text(json.dumps(timing, indent=1))
    print(json.dumps(timing, indent=1))
    print((out / f"main_{args.object}_{args.profile}.md").read_text())


if __name__ == "__main__":
    main()
