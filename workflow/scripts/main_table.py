"""Main and target-wise tables of one object."""
import sys

import pandas as pd

from knockgs_core.reporting import main_table, targetwise_table, write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
out = snakemake.output
evals = pd.concat([pd.read_csv(f) for f in snakemake.input.metrics], ignore_index=True)
obj = snakemake.wildcards.object
note = (f"Profile `{p.profile}`. Mean (and sample sd) over {evals['target'].nunique()} held-out targets; "
        f"trajectory RMSE over Gaussian-associated particles and all exported frames [normalized-domain m]. "
        f"Probe A = {p.probes[0]}; Probe B = {', '.join(p.probes[1:])}. "
        f"parameter_nearest_oracle reads the hidden target (diagnostic only).")
write_table(main_table(evals, p.methods, p.probes), out.csv, out.md, title=f"Main table: {obj}", note=note)
write_table(targetwise_table(evals, p.methods, p.probes), out.targetwise, out.targetwise_md, title=f"Target-wise results: {obj}",
            note=note)
