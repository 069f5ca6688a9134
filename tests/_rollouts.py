"""Helpers of the evaluation tests: small synthetic rollout files, one per theta."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from knockgs_core.rollout import Rollout, theta_tag, write_rollout


def theta_rollouts(folder: Path, thetas, probe: str, *, frames: int = 6, n_gs: int = 40, n_fill: int = 5,
                   seed: int = 5) -> dict[str, Path]:
    """Write a rollout per theta under ``probe`` (particles drifting at a theta-dependent rate)
    into ``folder``; returns ``{"probe/theta_tag": path}``."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.5, 1.5, size=(n_gs + n_fill, 3)).astype(np.float32)
    paths = {}
    for th in sorted(thetas):
        rate = rng.normal(scale=1e-3 * th[0] / th[1], size=(1, n_gs + n_fill, 3))
        X = (x0[None] + np.arange(frames)[:, None, None] * rate).astype(np.float32)
        path = Path(folder) / f"{probe}_{theta_tag(th)}.parquet"
        write_rollout(path, Rollout(X, None, {"n_gs": n_gs, "n_fill": n_fill, "export_times": list(range(frames))}))
        paths[f"{probe}/{theta_tag(th)}"] = path
    return paths
