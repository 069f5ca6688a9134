"""Render every frame of one theta's evaluation rollouts, one file per probe
(float16 RGB + alpha, compressed)."""
import sys
import time

import numpy as np

from knockgs_core.assets import read_ply
from knockgs_core.experiments import camera_from_contract, render_rollout
from knockgs_core.rollout import read_deformation, read_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
inp = snakemake.input
scene = np.load(inp.scene)
gaussians = read_ply(inp.ply)
cam = camera_from_contract(p.camera, width=p.width, height=p.height)
for rollout, F_path, frames in zip(inp.rollouts, inp.F, snakemake.output.frames):
    t0 = time.perf_counter()
    ro = read_rollout(rollout)
    F = read_deformation(F_path)
    rgb, alpha = render_rollout(gaussians, scene["static_mask"], scene["gaussian_index"], ro.positions, F, cam, device=p.device)
    np.savez_compressed(frames, rgb=rgb.astype(np.float16), alpha=alpha.astype(np.float16))
    print(f"{frames}: {len(rgb)} frames, {time.perf_counter() - t0:.2f} s", file=log, flush=True)
