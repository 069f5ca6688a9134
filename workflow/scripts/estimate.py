"""Frozen estimates of one deployable method (library + Probe-A queries only)."""
import sys

from knockgs_core.experiments import frozen_estimate
from knockgs_core.io import write_json

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
doc = frozen_estimate(p.method, snakemake.input.library, snakemake.input.queries, dict(p.options), config_hash=p.config_hash)
doc["rule_inputs"] = [str(f) for f in snakemake.input]
write_json(snakemake.output.json, doc, indent=1)
