"""The discrepancy loop on one case's measured files -> report folder."""
import sys
from pathlib import Path

from knockgs_core.io import check_job_inputs
from knockgs_core.discrepancy import run_files

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
inp = snakemake.input
floor = inp.floor if "floor" in inp.keys() else []
floor = [floor] if isinstance(floor, str) else list(floor)  # a world case's floor table, or none
run_files(p.object, p.profile, inp.measured, Path(snakemake.output.report).parent, particles=inp.particles, probe=p.probe,
          heldout_probes=[p.heldout_probe], heldout_measured={p.heldout_probe: inp.heldout}, library_rollouts=list(p.library),
          device=p.device, deterministic=p.deterministic, n_grid=p.loop_n_grid if floor else p.n_grid,
          floor_table=floor[0] if floor else None, smallest_effect=p.smallest_effect,
          progress=lambda msg: print(msg, file=log, flush=True))
