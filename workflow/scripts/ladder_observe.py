"""Every rung of the observation ladder for one job's rollouts: each rollout rendered with
depth (the profile's render size), observed, described; one row per (case, rung)."""
import sys

import pandas as pd

from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.assets import load_scene, read_ply
from knockgs_core.descriptors import FEATURE_NAMES
from knockgs_core.experiments import LadderSettings, camera_from_contract, rung_descriptors
from knockgs_core.observe import render_rgbd
from knockgs_core.rollout import read_deformation, read_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
s = p.settings
settings = LadderSettings(depth_noise=tuple(s["depth_noise"]), depth_tol=s["depth_tol"], track=dict(s["track"]), seed=s["seed"])
gaussians = read_ply(snakemake.input.ply)
static_mask, gaussian_index = load_scene(snakemake.input.scene, n_gaussians=len(gaussians))
camera = camera_from_contract(p.camera, width=p.width, height=p.height)
rows = []
for run in p.runs:
    ro = read_rollout(run["rollout"])
    F = read_deformation(run["F"])
    frames = render_rgbd(gaussians, static_mask, gaussian_index, ro.positions, F, camera,
                         frame_dt=ro.meta["probe"]["export"]["frame_dt"], device=p.device)
    phis, info = rung_descriptors(ro.positions, int(ro.meta["n_gs"]), frames, run["theta"], settings, source=run["rollout"])
    print(f"{run['case_name']}: {info}", file=log, flush=True)
    for rung, phi in phis.items():
        rows.append({"case_name": run["case_name"], "rung": rung, **dict(zip(FEATURE_NAMES, phi)), **info})
write_text(snakemake.output.table, pd.DataFrame(rows).to_csv(index=False, float_format="%.10g", lineterminator="\n"))
