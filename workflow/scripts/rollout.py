"""One MPM rollout (object, theta, probe) -> Parquet (+ deformation gradients)."""
import sys

from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.rollout import run_rollout, write_deformation, write_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
contract = load_contract(snakemake.wildcards.object, p.profile)
particles = load_particles(snakemake.input.particles)


def progress(frame, n_frames, stats):
    if frame % 5 == 0 or frame == n_frames - 1:
        print(f"frame {frame}/{n_frames - 1} cfl {stats['cfl']:.3g}", file=log, flush=True)


ro = run_rollout(contract, p.theta, p.probe, particles=particles, device=p.device, export_F=p.export_F, progress=progress)
write_rollout(snakemake.output.rollout, ro)
if p.export_F:
    write_deformation(snakemake.output.F, ro)
print(f"done: {ro.meta['stats']['steps']} substeps, {ro.meta['wall_seconds']:.2f} s", file=log)
