"""Parameter-nearest oracle (reads hidden target labels; evaluation-only diagnostic)."""
import sys

from knockgs_core.contract import load_targets
from knockgs_core.experiments import oracle_estimate, write_json

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
if p.options:
    raise SystemExit(f"method_params.parameter_nearest_oracle: {sorted(p.options)}: "
                     "knockgs_core.experiments.oracle_estimate takes no options yet")
targets = load_targets(snakemake.wildcards.split, snakemake.input.targets)
doc = oracle_estimate(snakemake.input.library, targets, config_hash=p.config_hash)
doc["rule_inputs"] = [str(f) for f in snakemake.input]
write_json(doc, snakemake.output.json)
