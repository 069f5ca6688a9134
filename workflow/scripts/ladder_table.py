"""The observation ladder's table and figure: per rung and method, the frozen estimates'
joint error and Probe-B trajectory RMSE against the hidden targets."""
import json
import sys

import numpy as np
import pandas as pd

from knockgs_core.io import check_job_inputs
from knockgs_core.contract import load_targets
from knockgs_core.experiments import ladder_note, ladder_table, plot_ladder
from knockgs_core.metrics import joint_error_pct, trajectory_rmse
from knockgs_core.reporting import write_table
from knockgs_core.rollout import read_rollout, theta_tag

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
targets = load_targets(p.split, snakemake.input.targets)
truth = {r.case_name: (float(r.E_scale), float(r.density_scale)) for r in targets.itertuples(index=False)}
cache = {}


def positions(theta):
    tag = theta_tag(theta)
    if tag not in cache:
        ro = read_rollout(p.rollouts[tag])
        cache[tag] = ro.positions[:, : int(ro.meta["n_gs"])]
    return cache[tag]


rows = []
files = iter(snakemake.input.estimates)
for rung in p.rungs:
    for m in p.methods:
        with open(next(files)) as fh:
            doc = json.load(fh)
        for pred in doc["predictions"]:
            est, th = (pred["E_scale"], pred["density_scale"]), truth[pred["case_name"]]
            rows.append({"rung": rung, "method": m, "target": pred["case_name"], "E_hat": est[0], "rho_hat": est[1],
                         "joint_error_pct": joint_error_pct(est, th),
                         "traj_rmse_probe_b": trajectory_rmse(positions(est), positions(th))})
table = ladder_table(pd.DataFrame(rows), p.rungs, p.methods)
obs = pd.concat([pd.read_csv(f) for f in snakemake.input.observations], ignore_index=True).drop_duplicates("case_name")
info = {"median_tracks": float(np.median(obs["tracks"])), "median_visible": float(np.median(obs["visible_particles"]))}
obj = snakemake.wildcards.object
write_table(table, snakemake.output.csv, snakemake.output.md, title=f"Observation ladder: {obj} ({len(truth)} targets)",
            note=ladder_note(table, p.probe_b, info))
plot_ladder(table, snakemake.output.png, title=f"{obj}: observation ladder (joint error per rung)")
