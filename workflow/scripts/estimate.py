"""Frozen estimates of every deployable method of a job (one file a method) from one library
and one Probe-A query descriptor table only: the main route's split, the passive route's, or a
rung of the observation ladder."""
import sys

from knockgs_core.experiments import frozen_estimate
from knockgs_core.io import write_json

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
for method, out in zip(p.methods, snakemake.output.json, strict=True):
    doc = frozen_estimate(method, snakemake.input.library, snakemake.input.queries, dict(p.options[method]),
                          config_hash=p.config_hash)
    doc["rule_inputs"] = [str(f) for f in snakemake.input]
    write_json(out, doc, indent=1)
