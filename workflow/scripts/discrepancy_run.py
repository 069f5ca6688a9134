"""The discrepancy loop on one case's measured files -> report folder."""
import sys
from pathlib import Path

from knockgs_core.discrepancy import run_files
from knockgs_core.sim import set_config

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
set_config(deterministic=p.deterministic)  # the GPU's reproducible P2G for every simulation of the job
inp = snakemake.input
run_files(p.object, p.profile, inp.measured, Path(snakemake.output.report).parent, particles=inp.particles, probe=p.probe,
          heldout_probes=[p.heldout_probe], heldout_measured={p.heldout_probe: inp.heldout}, library_rollouts=list(p.library),
          device=p.device, progress=lambda msg: print(msg, file=log, flush=True))
