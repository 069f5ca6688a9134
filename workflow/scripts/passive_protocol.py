"""The object's passive protocol (gravity, no known force) and its invariance check."""
import sys

from knockgs_core.io import write_json
from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import passive_protocol
from knockgs_core.sim import set_config

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
set_config(deterministic=p.deterministic)  # the GPU's reproducible P2G for every simulation of the job
contract = load_contract(p.object, p.profile)
protocol, record = passive_protocol(contract, load_particles(snakemake.input.particles), device=p.device)
print(f"gravity {protocol.gravity}; invariance {record['invariance']}", file=log)
write_json(snakemake.output.json, record)
