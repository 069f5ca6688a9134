"""Candidate library table: labels + Probe-A descriptors."""
import sys

from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.contract import load_candidates
from knockgs_core.experiments import library_table

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
table = library_table(load_candidates(), snakemake.params.rollouts, workers=snakemake.threads)
write_text(snakemake.output.table, table.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
