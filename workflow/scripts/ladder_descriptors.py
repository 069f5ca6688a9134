"""One descriptor table per rung: the library's (labels + descriptors, candidates.csv order)
or the queries' (descriptors only)."""
import sys

import pandas as pd

from knockgs_core.io import write_text
from knockgs_core.contract import load_candidates
from knockgs_core.descriptors import FEATURE_NAMES

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
obs = snakemake.input.observations
obs = pd.concat([pd.read_csv(f, dtype={"case_name": str}) for f in ([obs] if isinstance(obs, str) else obs)], ignore_index=True)
for rung, out in zip(p.rungs, snakemake.output.tables):
    rows = obs[obs["rung"] == rung][["case_name", *FEATURE_NAMES]]
    if p.labels:
        labels = load_candidates()[["case_name", "E_scale", "density_scale"]]
        rows = labels.merge(rows, on="case_name", how="left", validate="1:1")
        if rows[list(FEATURE_NAMES)].isna().any().any():
            raise SystemExit(f"ladder rung {rung}: a candidate has no descriptor")
    write_text(out, rows.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
