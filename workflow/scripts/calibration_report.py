"""The calibration's table and one-page report (figure + Markdown): the frozen estimate with
its interval and condition number, the Probe-A predictions observed against the measurement,
the held-out probes' predictions before and after."""
import json
import sys

import numpy as np
import pandas as pd

from knockgs_core.experiments import calibration_report, calibration_rows, estimate_summary, plot_calibration
from knockgs_core.io import write_text
from knockgs_core.metrics import rms_displacement_curve
from knockgs_core.reporting import write_table
from knockgs_core.rollout import read_rollout

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
# the prediction and frame folders, in p.predictions order
predicted = dict(zip(p.predictions, snakemake.input.predictions, strict=True))
rendered = dict(zip(p.predictions, snakemake.input.frames, strict=True))
with open(snakemake.input.estimate) as fh:
    summary = estimate_summary(json.load(fh))
with open(snakemake.input.measurement) as fh:
    measured = json.load(fh)
observed = pd.read_csv(snakemake.input.observed).set_index("case_name")
curve_cols = [c for c in observed.columns if c.startswith("r_")]
tracked = {which: observed.loc[which, curve_cols].to_numpy(dtype=float) for which in p.predictions}
thetas = {which: (float(observed.loc[which, "E_scale"]), float(observed.loc[which, "density_scale"])) for which in p.predictions}
positions, frame_dt = {}, None
for which in p.predictions:
    for probe in p.probes:
        ro = read_rollout(f"{predicted[which]}/{probe}.parquet")
        positions[(which, probe)] = ro.positions[:, : int(ro.meta["n_gs"])]
        frame_dt = float(ro.meta["probe"]["export"]["frame_dt"])
rows = calibration_rows(thetas, positions, tracked, measured["curve"], calibration_probe=p.probe)
write_table(rows, snakemake.output.csv, snakemake.output.md, title=f"Calibration of {p.object}: predictions before and after")
heldout = [probe for probe in p.probes if probe != p.probe]
curves = {(which, probe): rms_displacement_curve(positions[(which, probe)]) for probe in heldout for which in p.predictions}
peak = int(np.argmax(curves[("after", heldout[0])])) if heldout else 0
frames, alphas = {}, {}
for which in p.predictions:
    with np.load(f"{rendered[which]}/{heldout[0] if heldout else p.probe}.npz") as f:
        frames[which] = np.asarray(f["rgb"][peak], dtype=np.float32)
        alphas[which] = np.asarray(f["alpha"][peak], dtype=np.float32)
rows_in, cols_in = np.nonzero(np.maximum(*alphas.values()) > 0.01)  # the object's box in both frames, 6 px padding
if rows_in.size:
    crop = (slice(max(rows_in.min() - 6, 0), rows_in.max() + 7), slice(max(cols_in.min() - 6, 0), cols_in.max() + 7))
    frames = {which: rgb[crop] for which, rgb in frames.items()}
plot_calibration(snakemake.output.png, library=pd.read_csv(snakemake.input.library), summary=summary,
                 measured_curve=measured["curve"], observed=tracked, curves=curves, frames=frames,
                 frame_dt=frame_dt, title=f"{p.object}: calibrated from {p.measurement}")
info = {**measured, "measurement": p.measurement, "n_candidates": p.n_candidates,
        "tracker": ", ".join(f"{k} {v}" for k, v in measured["tracker"].items() if k in ("method", "radius", "max_seeds"))}
write_text(snakemake.output.report, calibration_report(p.object, summary, rows, info))
