"""Duration or contact shift table: every deployable method's frozen Probe-A estimates
re-simulated under the shift probes, against the targets' rollouts under the same probes."""
import json
import sys

from knockgs_core.io import check_job_inputs, ordered_map
from knockgs_core.contract import load_targets
from knockgs_core.experiments import contact_table, duration_table, evaluate_shift, protocol_distance, shift_note
from knockgs_core.reporting import write_table
from knockgs_core.rollout import read_rollout, theta_tag

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
estimates = {}
for m, path in zip(p.methods, snakemake.input.estimates):
    with open(path) as fh:
        estimates[m] = json.load(fh)
targets = load_targets(p.split, snakemake.input.targets)
targets = targets[targets["case_name"].isin(p.targets)].reset_index(drop=True)
evals = evaluate_shift(estimates, targets, lambda probe, th: p.rollouts[f"{probe}/{theta_tag(th)}"], p.probes,
                       workers=snakemake.threads)
if p.kind == "duration":
    table = duration_table(evals, p.methods)

    def protocol_pair(rec):
        """A target's GS-particle trajectories under Probe A and the shift probe, with their frame steps."""
        tag = theta_tag((float(rec.E_scale), float(rec.density_scale)))
        a = read_rollout(p.probe_a_rollouts[tag])
        b = read_rollout(p.rollouts[f"{p.probes[0]}/{tag}"])
        n = int(a.meta["n_gs"])
        return (a.positions[:, :n], a.meta["probe"]["export"]["frame_dt"], b.positions[:, :n],
                b.meta["probe"]["export"]["frame_dt"])

    dist = protocol_distance(ordered_map(protocol_pair, list(targets.itertuples(index=False)), workers=snakemake.threads))
    print(f"protocol distance: {dist}", file=log)
    table["protocol_distance_mean"] = dist["mean"]
    table["protocol_distance_sd"] = dist["sd"]
    note = shift_note(table, kind="duration", distance=dist)
    title = f"Duration shift ({p.probes[0]}): frozen Probe-A estimates, {len(targets)} targets"
else:
    table = contact_table(evals, p.methods, p.probes)
    note = shift_note(table, kind="contact")
    title = f"Contact location ({', '.join(p.probes)}): single-target demonstration, {targets['case_name'].iloc[0]}"
write_table(table, snakemake.output.csv, snakemake.output.md, title=title, note=note)
