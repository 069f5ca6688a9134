"""MPM rollouts of one job: (theta, probe) runs of one object -> one Parquet file each in the
job's output folder (+ deformation gradients). The contract, particles and Warp kernels are
loaded once. With an input ``protocol`` (a passive protocol's JSON), every run is under that
protocol instead of a contract probe."""
import json
import sys
from pathlib import Path

from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import PassiveProtocol
from knockgs_core.rollout import BackgroundWriter, run_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
# a job writes a folder of rollouts, or a single rollout (output "rollout")
folder = Path(snakemake.output.folder) if "folder" in snakemake.output.keys() else Path(snakemake.output.rollout).parent
for run in p.runs:
    for key in ("rollout", "F"):
        if run[key] is not None and Path(run[key]).parent != folder:
            raise SystemExit(f"rollout job: {run[key]} lies outside the job's output folder {folder}")
folder.mkdir(parents=True, exist_ok=True)
contract = load_contract(p.object, p.profile)
particles = load_particles(snakemake.input.particles)
passive = None
if "protocol" in snakemake.input.keys():
    with open(snakemake.input.protocol) as fh:
        passive = PassiveProtocol.from_dict(json.load(fh), snakemake.input.protocol)

# each finished rollout is written on a background thread while the next one simulates
with BackgroundWriter() as writer:
    for i, run in enumerate(p.runs):
        theta, probe = run["theta"], run["probe"]
        tag = f"[{i + 1}/{len(p.runs)}] theta ({theta[0]:.6f}, {theta[1]:.6f}) probe {probe}"

        def progress(frame, n_frames, stats, tag=tag):
            if frame % 5 == 0 or frame == n_frames - 1:
                print(f"{tag}: frame {frame}/{n_frames - 1} cfl {stats['cfl']:.3g}", file=log, flush=True)

        extra = {} if passive is None else passive.run_kwargs()
        ro = run_rollout(contract, theta, probe, particles=particles, device=p.device, export_F=run["F"] is not None,
                         progress=progress, **extra)
        writer.submit(run["rollout"], ro, run["F"])
        print(f"{tag}: done, {ro.meta['stats']['steps']} substeps, {ro.meta['wall_seconds']:.2f} s", file=log, flush=True)
