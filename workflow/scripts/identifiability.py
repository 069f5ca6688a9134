"""Descriptor identifiability of one object's library: pair distances, local-ridge condition numbers."""
import sys

import pandas as pd

from knockgs_core.io import check_job_inputs
from knockgs_core.experiments import condition_table, identifiability_summary, pair_table, plot_identifiability
from knockgs_core.reporting import write_table

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
inp, out = snakemake.input, snakemake.output
obj = snakemake.wildcards.object
library = pd.read_csv(inp.library, dtype={"case_name": str})
queries = pd.read_csv(inp.queries, dtype={"case_name": str})
pairs = pair_table(library, dict(p.rollouts))
k, alpha = int(p.local.get("k", 10)), float(p.local.get("alpha", 1e-3))
cond = condition_table(library, queries, k=k, alpha=alpha)
summary = identifiability_summary(pairs, cond)
write_table(summary, out.csv, out.md, title=f"Descriptor identifiability: {obj}",
            note=(f"Profile `{p.profile}`. Descriptor distance: Euclidean in the candidates' standardized 5-D descriptor; "
                  f"parameter distance: Euclidean in (log s_E, log s_rho); trajectory RMSE: between the two candidates' "
                  f"Probe-A rollouts [normalized-domain m]. Condition numbers of local ridge's centred k x 5 "
                  f"neighbourhood design (k = {k}), alone and with sqrt(alpha) I appended (alpha = {alpha:g}), at every "
                  f"candidate (leave-one-out) and every target. Every pair: identifiability_pairs_{obj}.csv."))
write_table(pairs, out.pairs)
plot_identifiability(pairs, cond, out.png, title=f"{obj}: descriptor identifiability ({p.profile})")
