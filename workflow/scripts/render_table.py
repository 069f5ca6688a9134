"""Rendered-frame table of one object: one row per method."""
import sys

import pandas as pd

from knockgs_core.reporting import render_table, write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
rows = pd.concat([pd.read_csv(f) for f in snakemake.input.metrics], ignore_index=True)
note = (f"Profile `{p.profile}`. Foreground PSNR [dB] pooled over frames and the target/prediction mask union; "
        f"object-crop SSIM averaged over frames; mean over targets.")
write_table(render_table(rows, p.methods, p.probes), snakemake.output.csv, snakemake.output.md,
            title=f"Rendered frames: {snakemake.wildcards.object}", note=note)
