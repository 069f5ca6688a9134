"""The discrepancy loop on one case's measured files -> report folder."""
import sys

from knockgs_core.discrepancy import run_files

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
inp = snakemake.input
run_files(p.object, p.profile, inp.measured, snakemake.output.report.rsplit("/", 1)[0], particles=inp.particles, probe=p.probe,
          heldout_probes=[p.heldout_probe], heldout_measured={p.heldout_probe: inp.heldout}, library_rollouts=list(inp.library),
          device=p.device, progress=lambda msg: print(msg, file=log, flush=True))
