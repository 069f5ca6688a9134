"""Passive versus active: every deployable method's estimates from Probe-A responses and
from passive responses, against the hidden targets."""
import json
import sys

from knockgs_core.io import write_text
from knockgs_core.contract import load_targets
from knockgs_core.experiments import passive_active_note, passive_active_table, plot_passive_active
from knockgs_core.reporting import write_table

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params


def load(paths):
    out = {}
    for m, path in zip(p.methods, paths):
        with open(path) as fh:
            out[m] = json.load(fh)
    return out


with open(snakemake.input.protocol) as fh:
    record = json.load(fh)
targets = load_targets(p.split, snakemake.input.targets)
summary, rows = passive_active_table({"active": load(snakemake.input.active), "passive": load(snakemake.input.passive)},
                                     targets, p.methods)
write_table(summary, snakemake.output.csv, snakemake.output.md,
            title=f"{p.object}: passive versus active observation ({len(targets)} targets, split {p.split})",
            note=passive_active_note(summary, [record]))
write_text(snakemake.output.rows, rows.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
plot_passive_active(rows, snakemake.output.png, title=f"{p.object}: local ridge, Probe A vs passive (dashed: s_E/s_rho const)")
