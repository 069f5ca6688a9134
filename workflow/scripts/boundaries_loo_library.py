"""Leave-one-object-out: the shared library of the other objects' candidate tables."""
import sys

import pandas as pd

from knockgs_core.io import write_text
from knockgs_core.experiments import shared_library

sys.stderr = open(snakemake.log[0], "w")
tables = {o: pd.read_csv(f) for o, f in zip(snakemake.params.objects, snakemake.input.libraries)}
write_text(snakemake.output.table, shared_library(tables).to_csv(index=False, float_format="%.10g", lineterminator="\n"))
