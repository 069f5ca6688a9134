"""Boundaries figure of one object: joint error per (condition, library), red = violates the library contract."""
import sys

import pandas as pd

from knockgs_core.reporting import plot_boundaries

sys.stderr = open(snakemake.log[0], "w")
plot_boundaries(pd.read_csv(snakemake.input.csv), snakemake.output[0],
                title=f"{snakemake.wildcards.object} ({snakemake.params.profile} profile): local ridge, Probe A")
