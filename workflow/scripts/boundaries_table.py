"""Boundaries table of one object: joint error and Probe-B RMSE per (condition, library)."""
import json
import sys

import pandas as pd

from knockgs_core.experiments import boundary_note, boundary_table
from knockgs_core.reporting import write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
metrics = pd.concat([pd.read_csv(f) for f in snakemake.input.metrics], ignore_index=True)
summaries = {}
for f in snakemake.input.summaries:
    with open(f) as fh:
        s = json.load(fh)
    summaries[s["condition"]] = s
table = boundary_table(metrics, summaries, probe=p.probe_b)
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"Discretization boundaries: {snakemake.wildcards.object}",
            note=boundary_note(table, profile=p.profile, probe_a=p.probe_a, probe_b=p.probe_b))
