"""Leave-one-object-out table: the shared estimator on each held-out object beside its own library."""
import sys

import pandas as pd

from knockgs_core.experiments import loo_table
from knockgs_core.reporting import write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
metrics = {o: pd.read_csv(f) for o, f in zip(p.objects, snakemake.input.metrics)}
own = {o: pd.read_csv(f) for o, f in zip(p.objects, snakemake.input.own)}
table = loo_table(metrics, own, probes=p.probes, trained_on=p.trained_on)
note = (f"Profile `{p.profile}`. Local ridge from Probe A with one library of the other objects' candidates "
        "(a shared estimator), applied to the held-out object's five targets; own: the object's own library "
        "(main table). traj_rmse_b: frozen write-back under the object's Probe B [normalized-domain m].")
write_table(table, snakemake.output.csv, snakemake.output.md, title="Leave-one-object-out", note=note)
