"""Write-back evaluation of one set of frozen estimates under Probe A and each Probe B (the main
benchmark and the boundaries study); ``params.labels`` become the first columns."""
import json
import sys

from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.contract import load_targets
from knockgs_core.experiments import evaluate_method
from knockgs_core.rollout import theta_tag

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
with open(snakemake.input.estimate) as fh:
    est = json.load(fh)
targets = load_targets(p.split, snakemake.input.targets)
df = evaluate_method(est, targets, lambda probe, th: p.rollouts[f"{probe}/{theta_tag(th)}"], p.probes,
                     workers=snakemake.threads)
for i, (key, value) in enumerate(p.labels.items()):
    df.insert(i, key, value)
write_text(snakemake.output.table, df.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
