"""Write one planted-effect case: measured files and, apart, its truth."""
import sys
from pathlib import Path

from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.discrepancy import default_cases, make_case, world_cases

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
out = snakemake.output
cases = default_cases(targets_path=snakemake.input.targets) + world_cases(targets_path=snakemake.input.targets)
spec = {c.name: c for c in cases}[snakemake.wildcards.case]
make_case(spec, load_contract(p.object, p.profile, n_grid=p.n_grid), load_particles(snakemake.input.particles),
          measured_dir=Path(out.calib).parent, truth_dir=Path(out.truth).parent, device=p.device,
          deterministic=p.deterministic)
