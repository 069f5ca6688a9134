"""The calibration's library table: labels + the observed descriptors, in candidates.csv order."""
import sys

import pandas as pd

from knockgs_core.descriptors import FEATURE_NAMES
from knockgs_core.io import write_text

sys.stderr = open(snakemake.log[0], "w")
obs = pd.concat([pd.read_csv(f, dtype={"case_name": str}) for f in snakemake.input.observations], ignore_index=True)
table = obs.set_index("case_name").loc[list(snakemake.params.cases)].reset_index()
write_text(snakemake.output.table, table[["case_name", "E_scale", "density_scale", *FEATURE_NAMES]].to_csv(
    index=False, float_format="%.10g", lineterminator="\n"))
