"""One object's main benchmark at paper scale on a GPU, timed stage by stage.

Runs the same library functions as the workflow rules (asset -> 54 candidate Probe-A
rollouts -> descriptors -> calibration -> frozen write-back under Probe A and each Probe B
-> trajectory metrics) in one process, for machines without Snakemake. Writes the main
table and a timing JSON to ``--out``.

    python3 benchmarks/paper_gpu.py --object pillow --profile paper --device cuda:0 --out OUT
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import pandas as pd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--out", required=True)
    ap.add_argument("--rollouts-only", action="store_true", help="time the asset and one rollout per evaluation probe, then stop")
    ap.add_argument("--methods", nargs="+", default=["fixed_default", "response_nearest", "response_knn", "global_ridge", "local_ridge", "parameter_nearest_oracle"])
    args = ap.parse_args()

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_candidates, load_contract, load_targets
    from knockgs_core.experiments import estimate_thetas, evaluate_method, frozen_estimate, library_table, oracle_estimate, query_table
    from knockgs_core.reporting import main_table, write_table
    from knockgs_core.rollout import run_rollout, theta_tag, write_rollout

    out = Path(args.out)
    ro_dir = out / "rollouts"
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    contract = load_contract(args.object, args.profile)
    built = build_asset(contract)
    ps = built.particles
    timing["asset_s"] = time.perf_counter() - t0
    print(f"asset: {ps.n_gs} GS + {ps.n_fill} fill particles in {timing['asset_s']:.1f} s", flush=True)

    roll_times = []
    if args.rollouts_only:
        rows = []
        for probe in [contract.roles["calibration"]] + list(contract.roles["heldout"]):
            t = time.perf_counter()
            ro = run_rollout(contract, (1.0, 1.0), probe, particles=ps, device=args.device)
            t_sim = time.perf_counter() - t
            t = time.perf_counter()
            write_rollout(out / f"{probe}.parquet", ro)
            rows.append({"probe": probe, "substeps": ro.meta["stats"]["steps"], "simulate_s": t_sim, "write_s": time.perf_counter() - t,
                         "particles": ps.n_gs + ps.n_fill, "max_cfl": ro.meta["stats"]["max_cfl"]})
            print(rows[-1], flush=True)
        timing["rollouts"] = rows
        (out / "timing.json").write_text(json.dumps(timing, indent=1))
        return

    def rollout(probe, theta):
        path = ro_dir / probe / f"{theta_tag(theta)}.parquet"
        if not path.exists():
            t = time.perf_counter()
            ro = run_rollout(contract, theta, probe, particles=ps, device=args.device)
            roll_times.append(time.perf_counter() - t)
            write_rollout(path, ro)
        return str(path)

    probe_a = contract.roles["calibration"]
    probes = [probe_a] + list(contract.roles["heldout"])
    cands = load_candidates()
    targets = load_targets("main")
    t = time.perf_counter()
    lib_paths = {r.case_name: rollout(probe_a, (r.E_scale, r.density_scale)) for r in cands.itertuples(index=False)}
    timing["library_rollouts_s"] = time.perf_counter() - t
    print(f"library: {len(lib_paths)} rollouts in {timing['library_rollouts_s']:.1f} s", flush=True)
    lib = library_table(cands, lib_paths)
    lib.to_csv(out / "library.csv", index=False)
    q = query_table({r.case_name: rollout(probe_a, (r.E_scale, r.density_scale)) for r in targets.itertuples(index=False)})
    q.to_csv(out / "queries_main.csv", index=False)
    params = {"response_knn": {"k": "cv"}, "global_ridge": {"alpha": "cv"}, "local_ridge": {"k": 10, "alpha": 1e-3}}
    t = time.perf_counter()
    evals = []
    for m in args.methods:
        est = oracle_estimate(out / "library.csv", targets) if m == "parameter_nearest_oracle" else frozen_estimate(m, out / "library.csv", out / "queries_main.csv", params.get(m, {}))
        for th in list(estimate_thetas(est).values()) + [(r.E_scale, r.density_scale) for r in targets.itertuples(index=False)]:
            for p in probes:
                rollout(p, th)
        df = evaluate_method(est, targets, lambda p, th: ro_dir / p / f"{theta_tag(th)}.parquet", probes)
        df.insert(0, "method", m)
        evals.append(df)
    timing["writeback_and_metrics_s"] = time.perf_counter() - t
    evals = pd.concat(evals, ignore_index=True)
    table = main_table(evals, args.methods, probes)
    write_table(table, out / f"main_{args.object}_{args.profile}.csv", out / f"main_{args.object}_{args.profile}.md", title=f"Main table: {args.object} ({args.profile} profile, {args.device})")
    timing["rollouts"] = len(roll_times)
    timing["median_rollout_s"] = float(pd.Series(roll_times).median())
    timing["total_s"] = time.perf_counter() - t0
    (out / "timing.json").write_text(json.dumps(timing, indent=1))
    print(json.dumps(timing, indent=1))
    print((out / f"main_{args.object}_{args.profile}.md").read_text())


if __name__ == "__main__":
    main()
