"""Target query table: Probe-A descriptors only, no labels."""
import sys

from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.experiments import query_table

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
table = query_table(dict(zip(snakemake.params.names, snakemake.params.rollouts)), workers=snakemake.threads)
write_text(snakemake.output.table, table.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
