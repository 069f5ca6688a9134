"""Render every frame of one evaluation rollout (float16 RGB + alpha, compressed)."""
import sys

import numpy as np

from knockgs_core.assets import read_ply
from knockgs_core.experiments import camera_from_contract, render_rollout
from knockgs_core.rollout import read_deformation, read_rollout

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
scene = np.load(snakemake.input.scene)
ro = read_rollout(snakemake.input.rollout)
F = read_deformation(snakemake.input.F)
cam = camera_from_contract(p.camera, width=p.width, height=p.height)
rgb, alpha = render_rollout(read_ply(snakemake.input.ply), scene["static_mask"], scene["gaussian_index"], ro.positions, F, cam, device=p.device)
np.savez_compressed(snakemake.output.frames, rgb=rgb.astype(np.float16), alpha=alpha.astype(np.float16))
