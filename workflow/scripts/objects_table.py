"""Three-object repeatability table and figure."""
import sys

import pandas as pd

from knockgs_core.reporting import objects_table, plot_objects, write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
mains = {o: pd.read_csv(f) for o, f in zip(p.objects, snakemake.input.mains)}
t = objects_table(mains, p.heldout, calibration_probes=p.calibration)
write_table(t, snakemake.output.csv, snakemake.output.md, title="Object-specific repeatability",
            note=f"Profile `{p.profile}`. Mean over held-out targets; traj_rmse_B is the object's first held-out probe.")
plot_objects(t, snakemake.output.png)
