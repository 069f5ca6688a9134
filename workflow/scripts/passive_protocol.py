"""The object's passive protocol (gravity, no known force) and its invariance check."""
import sys

from knockgs_core.io import write_json
from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.experiments import passive_protocol

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
contract = load_contract(p.object, p.profile)
protocol, record = passive_protocol(contract, load_particles(snakemake.input.particles), device=p.device,
                                    deterministic=p.deterministic)
print(f"gravity {protocol.gravity}; invariance {record['invariance']}", file=log)
write_json(snakemake.output.json, record)
