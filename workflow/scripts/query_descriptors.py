"""Target query table: Probe-A descriptors only, no labels."""
import sys

from knockgs_core.experiments import query_table

sys.stderr = open(snakemake.log[0], "w")
query_table(dict(zip(snakemake.params.names, snakemake.input.rollouts))).to_csv(snakemake.output.table, index=False, float_format="%.10g")
