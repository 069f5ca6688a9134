"""Build an object's asset: normalized 3DGS PLY, simulated particles, render scene data."""
import json
import sys

from knockgs_core.io import write_json
from knockgs_core.assets import asset_figure, build_asset, save_particles, save_scene, write_ply
from knockgs_core.contract import load_contract

sys.stderr = open(snakemake.log[0], "w")
# a contract by name (the object wildcard), or by its file where the rule gives one (params.contract)
contract = load_contract(getattr(snakemake.params, "contract", None) or snakemake.wildcards.object, snakemake.params.profile,
                         n_grid=getattr(snakemake.params, "n_grid", None))
built = build_asset(contract)
write_ply(built.gaussians, snakemake.output.ply)
save_particles(built.particles, snakemake.output.particles, contract=contract)
save_scene(built, snakemake.output.scene)
summary = {"object": contract.name, "profile": contract.profile, "contract_hash": contract.hash, **built.summary()}
write_json(snakemake.output.summary, summary, indent=1)
print(json.dumps(summary, default=int), file=sys.stderr)
asset_figure(built, snakemake.output.figure, title=f"{contract.name} ({contract.profile}): GS vs fill particles")
