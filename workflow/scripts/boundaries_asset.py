"""The asset of one boundary condition: the changed contract's particles, counts and probe force factors."""
import json
import sys

from knockgs_core.io import write_json
from knockgs_core.assets import build_asset, save_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import BoundarySettings, condition_world

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
contract = load_contract(p.object, p.profile)
original = build_asset(contract).particles
world = condition_world(contract, p.condition, BoundarySettings.from_config(p.settings), original_particles=original)
save_particles(world.particles, snakemake.output.particles, contract=world.contract)
summary = world.summary(original)
write_json(snakemake.output.summary, summary, indent=1)
print(json.dumps(summary, default=str), file=sys.stderr)
