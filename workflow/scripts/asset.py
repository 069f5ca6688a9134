"""Build an object's asset: normalized 3DGS PLY, simulated particles, render scene data."""
import json
import sys

import numpy as np

from knockgs_core.assets import build_asset, save_particles, write_ply

try:
    from knockgs_core.assets import asset_figure
except ImportError:  # older releases kept it private
    from knockgs_core.assets._figure import asset_figure
from knockgs_core.contract import load_contract

sys.stderr = open(snakemake.log[0], "w")
contract = load_contract(snakemake.wildcards.object, snakemake.params.profile)
built = build_asset(contract)
write_ply(built.gaussians, snakemake.output.ply)
save_particles(built.particles, snakemake.output.particles)
np.savez_compressed(snakemake.output.scene, static_mask=built.static_mask, gaussian_index=built.particles.gaussian_index)
summary = {"object": contract.name, "profile": contract.profile, "contract_hash": contract.hash, **built.summary()}
with open(snakemake.output.summary, "w") as fh:
    json.dump(summary, fh, indent=1, default=int)
print(json.dumps(summary, default=int), file=sys.stderr)
asset_figure(built, snakemake.output.figure, title=f"{contract.name} ({contract.profile}): GS vs fill particles")
