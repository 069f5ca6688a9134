"""Render every frame of one theta's evaluation rollouts, one file per probe
(float16 RGB + alpha, compressed)."""
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from knockgs_core.io import check_files_in, check_job_inputs, staged_folders, write_npz
from knockgs_core.assets import load_scene, read_ply
from knockgs_core.render import camera_from_contract, render_rollout  # not the studies' package: a lighter import
from knockgs_core.rollout import read_deformation, read_rollout

log = open(snakemake.log[0], "w")
sys.stderr = log
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
gaussians = read_ply(snakemake.input.ply)
static_mask, gaussian_index = load_scene(snakemake.input.scene, n_gaussians=len(gaussians))
cam = camera_from_contract(p.camera, width=p.width, height=p.height)


def load(job):
    return read_rollout(job["rollout"]), read_deformation(job["F"])


def write(job, rgb, alpha, t0, stages):
    write_npz(stages.path(job["frames"]), rgb=rgb.astype(np.float16), alpha=alpha.astype(np.float16))
    print(f"{job['frames']}: {len(rgb)} frames, {time.perf_counter() - t0:.2f} s", file=log, flush=True)


# one file per probe, in a staging folder moved into place once all are written
# (staged_folders): a job stopped at any point leaves no folder, so a resumed run renders the
# theta again instead of taking a partial folder. While a probe renders, the next probe's
# rollout is read and the last one's frames are compressed and written, on two threads (the
# same files as in turn)
folder = Path(snakemake.output.folder)
jobs = list(p.jobs)
check_files_in([job["frames"] for job in jobs], [folder], source="render job")
with staged_folders(folder, log=log) as stages, ThreadPoolExecutor(max_workers=2) as pool:
    reading = pool.submit(load, jobs[0]) if jobs else None
    writes = []
    for i, job in enumerate(jobs):
        t0 = time.perf_counter()
        ro, F = reading.result()
        reading = pool.submit(load, jobs[i + 1]) if i + 1 < len(jobs) else None
        rgb, alpha = render_rollout(gaussians, static_mask, gaussian_index, ro.positions, F, cam, device=p.device)
        del ro, F
        writes.append(pool.submit(write, job, rgb, alpha, t0, stages))
    for w in writes:
        w.result()
