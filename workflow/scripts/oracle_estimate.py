"""Parameter-nearest oracle (reads hidden target labels; evaluation-only diagnostic)."""
import sys

from knockgs_core.contract import load_targets
from knockgs_core.experiments import oracle_estimate
from knockgs_core.io import write_json

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
targets = load_targets(snakemake.wildcards.split, snakemake.input.targets)
doc = oracle_estimate(snakemake.input.library, targets, dict(p.options), config_hash=p.config_hash)
doc["rule_inputs"] = [str(f) for f in snakemake.input]
write_json(snakemake.output.json, doc, indent=1)
