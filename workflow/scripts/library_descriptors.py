"""Candidate library table: labels + Probe-A descriptors."""
import sys

from knockgs_core.contract import load_candidates
from knockgs_core.experiments import library_table

sys.stderr = open(snakemake.log[0], "w")
cands = load_candidates()
rollouts = dict(zip(snakemake.params.cases, snakemake.input.rollouts))
library_table(cands, rollouts).to_csv(snakemake.output.table, index=False, float_format="%.10g")
