"""Collect the evaluated cases into the table of cases (CSV and Markdown) and its figure."""
import json
import sys

from knockgs_core.discrepancy import case_table, table_figure, write_case_table

sys.stderr = open(snakemake.log[0], "w")
df = case_table([json.loads(open(path).read()) for path in snakemake.input.rows])
title = getattr(snakemake.params, "title", None)
write_case_table(df, snakemake.output.csv, snakemake.output.md, **({"title": title} if title else {}))
table_figure(df, snakemake.output.figure)
