"""CMA-ES direct video optimization of one seed: every target of the split against its rendered
RGB-D Probe-A video, a fixed budget of simulator calls each, then frozen."""
import sys
import time
from pathlib import Path

from knockgs_core.contract import load_candidates, load_contract
from knockgs_core.experiments import (VideoScene, candidate_bounds, cmaes_calibrate, cmaes_estimate, rollout_video,
                                      video_simulator)
from knockgs_core.io import check_job_inputs, write_json

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
contract = load_contract(p.object, p.profile)
scene = VideoScene.from_files(contract, Path(snakemake.input.ply).parent, width=p.width, height=p.height)
simulate_render = video_simulator(contract, scene, probe=p.probe, device=p.device, deterministic=p.deterministic)
bounds = candidate_bounds(load_candidates(snakemake.input.candidates))
print(f"{contract.name} ({contract.profile}), seed {p.seed}: budget {p.budget}, render {p.width}x{p.height}, "
      f"bounds {bounds}, depth weight {p.depth_weight}", file=log, flush=True)
runs = {}
for name, files in p.targets.items():
    t0 = time.perf_counter()
    target = rollout_video(scene, files["rollout"], files["F"], device=p.device)
    runs[name] = cmaes_calibrate(simulate_render, target, bounds=bounds, budget=p.budget, seed=p.seed,
                                 depth_weight=p.depth_weight)
    r = runs[name]
    print(f"{name}: theta ({r['theta'][0]:.6f}, {r['theta'][1]:.6f}), loss {r['loss']:.6g} at call {r['best_call']} "
          f"of {r['calls']}, {time.perf_counter() - t0:.1f} s", file=log, flush=True)
settings = {"probe": p.probe, "width": p.width, "height": p.height, "depth_weight": p.depth_weight,
            "bounds": [list(b) for b in bounds], "device": p.device, "loss": "video_loss"}
doc = cmaes_estimate(runs, seed=p.seed, budget=p.budget, settings=settings)
doc["object"] = contract.name
doc["profile"] = contract.profile
doc["contract_hash"] = contract.hash
doc["config_hash"] = p.config_hash
doc["rule_inputs"] = [str(f) for f in snakemake.input]
write_json(snakemake.output.json, doc, indent=1)
