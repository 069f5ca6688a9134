"""CMA-ES video route table of one object: every seed's frozen estimates written back under
every evaluation probe, mean +- sd over seeds, per target and over targets."""
import json
import sys

from knockgs_core.io import check_job_inputs
from knockgs_core.contract import load_targets
from knockgs_core.errors import InputError
from knockgs_core.experiments import cmaes_note, cmaes_rows, cmaes_table
from knockgs_core.reporting import write_table
from knockgs_core.rollout import theta_tag

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
estimates = {}
for seed, path in zip(p.seeds, snakemake.input.estimates):
    with open(path) as fh:
        doc = json.load(fh)
    for key, want in (("seed", seed), ("budget", p.budget)):
        if doc.get(key) != want:
            raise InputError(path, key, f"{doc.get(key)!r}, the config says {want!r}")
    estimates[seed] = doc
targets = load_targets(p.split, snakemake.input.targets)
rows = cmaes_rows(estimates, targets, lambda probe, th: p.rollouts[f"{probe}/{theta_tag(th)}"],
                  lambda probe, th: p.frames[f"{probe}/{theta_tag(th)}"], p.probes)
print(rows.to_string(), file=log)
table = cmaes_table(rows, p.probes, budget=p.budget, library_rollouts=p.library_rollouts)
note = cmaes_note(table, budget=p.budget, seeds=p.seeds, width=p.width, height=p.height, profile=p.profile)
write_table(table, snakemake.output.csv, snakemake.output.md,
            title=f"CMA-ES direct video optimization: {snakemake.wildcards.object}", note=note)
