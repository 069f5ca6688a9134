"""MPM against the finite-element reference on the held block -> verification table."""
import sys

from knockgs_core.fem import VerificationSettings, verification_note, verification_study
from knockgs_core.reporting import write_table

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
settings = VerificationSettings.from_config(p.settings)
table = verification_study(settings, device=p.device, deterministic=p.deterministic,
                           log=lambda msg: print(msg, file=log, flush=True))
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"MPM vs finite-element reference ({p.profile})",
            note=verification_note(table, settings))
