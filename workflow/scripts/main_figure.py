"""Main figure of one object: parameter error bars and Probe A/B trajectory errors."""
import sys

import pandas as pd

from knockgs_core.reporting import plot_main

sys.stderr = open(snakemake.log[0], "w")
plot_main(pd.read_csv(snakemake.input.csv), snakemake.params.probes, snakemake.output[0],
          title=f"{snakemake.wildcards.object} ({snakemake.params.profile} profile)")
