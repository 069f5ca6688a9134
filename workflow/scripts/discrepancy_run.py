"""The discrepancy loop on one case's measured files -> report folder."""
import sys
from pathlib import Path

from knockgs_core.discrepancy import run_files

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
inp = snakemake.input
run_files(p.object, p.profile, inp.measured, Path(snakemake.output.report).parent, particles=inp.particles, probe=p.probe,
          heldout_probes=[p.heldout_probe], heldout_measured={p.heldout_probe: inp.heldout}, library_rollouts=list(p.library),
          device=p.device, deterministic=p.deterministic, progress=lambda msg: print(msg, file=log, flush=True))
