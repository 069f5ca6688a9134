"""Parameter-nearest oracle (reads hidden target labels; evaluation-only diagnostic)."""
import sys

from knockgs_core.contract import load_targets
from knockgs_core.experiments import oracle_estimate, write_json

sys.stderr = open(snakemake.log[0], "w")
doc = oracle_estimate(snakemake.input.library, load_targets(snakemake.wildcards.split, snakemake.input.targets), config_hash=snakemake.params.config_hash)
doc["rule_inputs"] = [str(f) for f in snakemake.input]
write_json(doc, snakemake.output.json)
