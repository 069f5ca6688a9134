"""Qualitative figure and animated comparison of one object."""
import sys

import numpy as np

from knockgs_core.io import check_job_inputs
from knockgs_core.reporting import comparison_gif, qualitative_figure

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
p = snakemake.params
frames = [np.load(f) for f in p.frames]
names = ["target"] + list(p.methods)
rgb = [f["rgb"].astype(np.float32) for f in frames]
alpha = [f["alpha"].astype(np.float32) for f in frames]
title = f"{snakemake.wildcards.object}: {p.target} under held-out {p.probe}"
qualitative_figure(names, rgb, alpha, snakemake.output.png, title=title)
pick = [names.index(n) for n in ("target", "local_ridge", "fixed_default") if n in names]
comparison_gif([names[i] for i in pick], [rgb[i] for i in pick], snakemake.output.gif)
