"""An object's MPM levels against the finite-element reference -> floor table and figure."""
import sys

from knockgs_core.contract import at_resolution, load_contract
from knockgs_core.experiments import FloorSettings, floor_note, floor_study, plot_floor
from knockgs_core.reporting import write_table

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
obj = snakemake.wildcards.object
settings = FloorSettings.from_config(p.settings)
contract = load_contract(obj, p.profile)
if getattr(p, "n_grid", None):  # the discrepancy loop's grid where it is not the profile's
    contract = at_resolution(contract, p.n_grid)
table = floor_study(contract, settings, device=p.device, deterministic=p.deterministic,
                    log=lambda msg: print(msg, file=log, flush=True))
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"Floor: {obj}'s MPM vs the FEM reference ({p.profile})",
            note=floor_note(table, contract, settings))
plot_floor(table, snakemake.output.png, title=f"{obj} ({p.profile}): MPM vs FEM reference")
