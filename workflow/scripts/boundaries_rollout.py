"""MPM rollouts of one boundary-condition job: (theta, probe) runs under the changed contract ->
one Parquet file each in the job's output folder. The condition's particles and probe force
factors come from its asset job."""
import json
import sys
from pathlib import Path

from knockgs_core.io import check_files_in, staged_folders
from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import BoundarySettings, condition_world
from knockgs_core.rollout import write_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
folder = Path(snakemake.output.folder)
check_files_in([run["rollout"] for run in p.runs], [folder], source="boundary rollout job")
for run in p.runs:
    if run["F"] is not None:
        raise SystemExit(f"boundary rollout job: {run['rollout']} asks for F, which boundary rollouts do not export")
with open(snakemake.input.summary) as fh:
    summary = json.load(fh)
world = condition_world(load_contract(p.object, p.profile), p.condition, BoundarySettings.from_config(p.settings),
                        particles=load_particles(snakemake.input.particles), force_factors=summary["force_factors"])
if world.contract.hash != summary["contract_hash"]:
    raise SystemExit(f"{snakemake.input.summary}: field 'contract_hash': the condition's contract changed since "
                     "its asset was built; rebuild the asset")
# built in a staging folder moved into place at the end: a job stopped at any point leaves no folder
with staged_folders(folder, log=log) as stages:
    for i, run in enumerate(p.runs):
        theta, probe = run["theta"], run["probe"]
        tag = f"[{i + 1}/{len(p.runs)}] {p.condition}: theta ({theta[0]:.6f}, {theta[1]:.6f}) probe {probe}"
        ro = world.rollout(theta, probe, device=p.device, deterministic=p.deterministic)
        write_rollout(stages.path(run["rollout"]), ro)
        print(f"{tag}: done, {ro.meta['stats']['steps']} substeps, {ro.meta['wall_seconds']:.2f} s", file=log, flush=True)
