"""Collect the evaluated cases into results/tables/discrepancy.csv|md."""
import json
import sys

from knockgs_core.discrepancy import case_table, write_table

sys.stderr = open(snakemake.log[0], "w")
rows = [json.loads(open(path).read()) for path in snakemake.input.rows]
write_table(case_table(rows), snakemake.output.csv, snakemake.output.md)
