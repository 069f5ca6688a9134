"""Convergence study of one object's Probe-A response (time and space) -> table + figure."""
import sys

from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import convergence_note, convergence_study, plot_convergence
from knockgs_core.reporting import write_table

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
contract = load_contract(p.object, p.profile)
particles = load_particles(snakemake.input.particles)
table = convergence_study(contract, particles, theta=tuple(p.theta), n_frames=p.n_frames, device=p.device,
                          deterministic=p.deterministic, log=lambda msg: print(msg, file=log, flush=True))
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"Probe-A convergence: {p.object}",
            note=convergence_note(table))
plot_convergence(table, snakemake.output.png, grid_lim=contract.sim.grid_lim,
                 title=f"{p.object} ({p.profile}), theta = ({p.theta[0]:g}, {p.theta[1]:g}), Probe A")
