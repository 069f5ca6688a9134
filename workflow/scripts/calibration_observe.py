"""Rollouts observed as the measurement: each rendered as RGB-D by the measurement's camera,
tracked with its tracker and described; one row per rollout (descriptor, tracked curve r_t)."""
import sys

import pandas as pd

from knockgs_core.assets import load_scene, read_ply
from knockgs_core.descriptors import FEATURE_NAMES
from knockgs_core.experiments import ObservationSettings, camera_from_dict, observe_rollout
from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.rollout import read_deformation, read_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
settings = ObservationSettings(**p.observation)
camera = camera_from_dict(p.camera)
gaussians = read_ply(snakemake.input.ply)
static_mask, gaussian_index = load_scene(snakemake.input.scene, n_gaussians=len(gaussians))
rows = []
for run in p.runs:
    ro = read_rollout(run["rollout"])
    phi, curve, info = observe_rollout(gaussians, static_mask, gaussian_index, ro.positions, read_deformation(run["F"]),
                                       camera, settings, frame_dt=ro.meta["probe"]["export"]["frame_dt"],
                                       device=p.device, source=run["rollout"])
    print(f"{run['case_name']}: {info}", file=log, flush=True)
    rows.append({"case_name": run["case_name"], "E_scale": run["theta"][0], "density_scale": run["theta"][1],
                 **dict(zip(FEATURE_NAMES, phi)), **info, **{f"r_{t:02d}": v for t, v in enumerate(curve)}})
write_text(snakemake.output.table, pd.DataFrame(rows).to_csv(index=False, float_format="%.10g", lineterminator="\n"))
