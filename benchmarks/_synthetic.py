"""Synthetic paper-scale trajectories shared by the reading and evaluation benchmarks."""

from __future__ import annotations

import numpy as np


def swaying_cloud(rng: np.random.Generator, frames: int, particles: int):
    """Rest positions ``x0`` [N, 3] in the unit box around 1 and a wave ``wave`` [T, 1, 1]
    (float32): a trajectory is ``x0 + amplitude * wave * direction``."""
    x0 = rng.uniform(0.5, 1.5, size=(particles, 3)).astype(np.float32)
    wave = np.sin(np.linspace(0.0, 6.0, frames, dtype=np.float32))[:, None, None]
    return x0, wave


def sway(rng: np.random.Generator, x0: np.ndarray, wave: np.ndarray) -> np.ndarray:
    """One trajectory [T, N, 3] (float32): every particle sways along a random direction, 2 cm at most."""
    return x0[None] + 0.02 * wave * rng.uniform(-1, 1, size=(1, x0.shape[0], 3)).astype(np.float32)
