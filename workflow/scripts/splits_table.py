"""Splits table and figure of one object: local ridge against the strongest other method per split."""
import sys

import pandas as pd

from knockgs_core.experiments import plot_splits, splits_note, splits_table
from knockgs_core.reporting import write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
obj = snakemake.wildcards.object
files = iter(snakemake.input.metrics)  # split-major, methods in table order; each row names its method
evals = {s: pd.concat([pd.read_csv(next(files)) for _ in p.methods], ignore_index=True) for s in p.splits}
table = splits_table(evals, p.methods, p.heldout)
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"Target splits: {obj}",
            note=f"Profile `{p.profile}`. " + splits_note(table, p.heldout, main=p.splits[0]))
plot_splits(table, snakemake.output.png, title=f"{obj}: target splits ({p.profile})")
