"""Foreground PSNR and crop SSIM of one method's frozen estimates."""
import json
import sys

from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.contract import load_targets
from knockgs_core.experiments import render_metrics_rows
from knockgs_core.rollout import theta_tag

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
with open(snakemake.input.estimate) as fh:
    est = json.load(fh)
targets = load_targets(snakemake.wildcards.split, snakemake.input.targets)
df = render_metrics_rows(est, targets, lambda probe, th: p.frames[f"{probe}/{theta_tag(th)}"], p.probes)
df.insert(0, "method", snakemake.wildcards.method)
write_text(snakemake.output.table, df.to_csv(index=False, float_format="%.8g", lineterminator="\n"))
