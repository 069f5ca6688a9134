"""MPM rollouts of one job: (theta, probe) pairs of one object -> one Parquet file each
(+ deformation gradients). The contract, particles and Warp kernels are loaded once."""
import sys

from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.rollout import run_rollout, write_deformation, write_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
out = snakemake.output
contract = load_contract(p.object, p.profile)
particles = load_particles(snakemake.input.particles)
runs = p.runs
if len(out.rollouts) != len(runs):
    raise SystemExit(f"rollout job: {len(runs)} runs but {len(out.rollouts)} output files")

for i, (theta, probe) in enumerate(runs):
    tag = f"[{i + 1}/{len(runs)}] theta ({theta[0]:.6f}, {theta[1]:.6f}) probe {probe}"

    def progress(frame, n_frames, stats, tag=tag):
        if frame % 5 == 0 or frame == n_frames - 1:
            print(f"{tag}: frame {frame}/{n_frames - 1} cfl {stats['cfl']:.3g}", file=log, flush=True)

    ro = run_rollout(contract, theta, probe, particles=particles, device=p.device, export_F=p.export_F, progress=progress)
    write_rollout(out.rollouts[i], ro)
    if p.export_F:
        write_deformation(out.F[i], ro)
    print(f"{tag}: done, {ro.meta['stats']['steps']} substeps, {ro.meta['wall_seconds']:.2f} s", file=log, flush=True)
