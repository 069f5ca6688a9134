"""The rendered truth of a track: where the surface point it started on went (private).

A rendered RGB-D sequence knows each pixel's 3-D point at frame 0 (its rendered depth through
the camera) and which Gaussians make that pixel (the compositing weights that blend its colour
and depth); the rollout knows how each Gaussian moved. The pixel's point moves by the same
blend of the Gaussians' displacements, which the renderer computes when the displacements are
drawn as colours. :func:`track_errors` compares tracks with that truth, in metres and pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._rgbd import project, unproject

__all__ = ["surface_truth", "TrackErrors", "track_errors"]


def surface_truth(gaussians, static_mask, positions, F, camera, rows0, cols0, depth0, *,
                  device: str = "cpu") -> np.ndarray:
    """True world trajectories [T, M, 3] [m] of the surface points seen at frame-0 pixels
    ``rows0``, ``cols0`` [M] (pixel centres at integers) with rendered camera depth
    ``depth0`` [M] [m]: the frame-0 point ``unproject(rows0, cols0, depth0)`` moved by the
    displacement the renderer blends at that pixel, ``sum_i w_i (x_i(t) - x_i(0))`` with
    ``w_i`` the compositing weights of frame 0 (those that blend its colour and depth; a
    static support's Gaussians take part with no displacement). Where the object alone makes
    the pixel (the tracker's seeds: :func:`knockgs_core.observe.render_rgbd`'s mask) the
    weights sum to its coverage, about 1.

    ``gaussians``, ``static_mask`` [N] as for :func:`knockgs_core.observe.render_rgbd`;
    ``positions`` [T, n_gs, 3] the Gaussian-associated particles' positions [m];
    ``F`` [T, n_gs, 3, 3] their deformation gradients (frame 0's shapes the weights)."""
    from ..render import deformed_scene, render

    X = np.asarray(positions, dtype=np.float64)
    mask = np.asarray(static_mask, dtype=bool)
    dyn = np.flatnonzero(~mask)
    if X.ndim != 3 or X.shape[1:] != (dyn.size, 3):
        raise InputError("truth", "positions", f"expected [T, {dyn.size}, 3], got {list(X.shape)}")
    means0 = np.asarray(gaussians.means, dtype=np.float64)
    cov0 = np.asarray(gaussians.covariances(), dtype=np.float64)
    opac = np.asarray(gaussians.opacities, dtype=np.float64)
    colors = np.full((len(means0), 3), 0.5)
    scene = deformed_scene(means0, cov0, colors, opac, X[0], np.asarray(F[0], dtype=np.float64), mask)
    P0 = unproject(camera, rows0, cols0, depth0)
    span = float(np.max(np.abs(X - X[0]))) or 1.0
    scale = 0.4 / span  # displacements as colours in [0.1, 0.9]
    ri = np.rint(np.asarray(rows0)).astype(np.int64)
    ci = np.rint(np.asarray(cols0)).astype(np.int64)
    if not (np.allclose(ri, rows0) and np.allclose(ci, cols0)):
        raise InputError("truth", "rows0", "frame-0 pixels must be pixel centres (integers)")
    out = np.empty((X.shape[0], len(P0), 3))
    out[0] = P0
    for t in range(1, X.shape[0]):
        # static Gaussians and the background: colour 0.5, no displacement
        colors[dyn] = 0.5 + scale * (X[t] - X[0])
        rgb = render(scene.means, scene.covariances, colors, scene.opacities, camera, background=(0.5, 0.5, 0.5),
                     device=device).rgb
        out[t] = P0 + (np.asarray(rgb, dtype=np.float64)[ri, ci] - 0.5) / scale
    return out


@dataclass(frozen=True)
class TrackErrors:
    """Tracks against their rendered truth (displacements from frame 0, frames 1..T-1).

    ``rms_m``: RMS per coordinate [m] of the 3-D error; ``rms_px``: RMS per image axis [px] of
    the error in the image; ``final_rms_m``: ``rms_m`` at the last frame; ``motion_px``: the
    median true image motion a frame [px]; ``total_motion_px``: the RMS true image
    displacement at the last frame [px]; ``signal_m``: the RMS per coordinate of the true
    displacement [m]; ``per_frame_m`` [T]: ``rms_m`` frame by frame (0 at frame 0)."""

    rms_m: float
    rms_px: float
    final_rms_m: float
    motion_px: float
    total_motion_px: float
    signal_m: float
    per_frame_m: np.ndarray

    def as_dict(self) -> dict:
        return {k: float(v) for k, v in self.__dict__.items() if k != "per_frame_m"}


def track_errors(camera, rows, cols, points, truth) -> TrackErrors:
    """Errors of tracks (``rows``, ``cols`` [T, M] in the image, ``points`` [T, M, 3] lifted,
    [m]) against their truth ``truth`` [T, M, 3] [m] (:func:`surface_truth`)."""
    P = np.asarray(points, dtype=np.float64)
    Q = np.asarray(truth, dtype=np.float64)
    e = (P - P[0]) - (Q - Q[0])
    per_frame = np.sqrt(np.mean(e**2, axis=(1, 2)))
    tr, tc, _ = project(camera, Q)
    er = (np.asarray(rows) - rows[0]) - (tr - tr[0])
    ec = (np.asarray(cols) - cols[0]) - (tc - tc[0])
    step = np.hypot(np.diff(tr, axis=0), np.diff(tc, axis=0))
    total = np.hypot(tr[-1] - tr[0], tc[-1] - tc[0])
    d = Q - Q[0]
    return TrackErrors(
        rms_m=float(np.sqrt(np.mean(e[1:] ** 2))),
        rms_px=float(np.sqrt(0.5 * np.mean(er[1:] ** 2 + ec[1:] ** 2))),
        final_rms_m=float(per_frame[-1]),
        motion_px=float(np.median(step)),
        total_motion_px=float(np.sqrt(np.mean(total**2))),
        signal_m=float(np.sqrt(np.mean(d[1:] ** 2))),
        per_frame_m=per_frame,
    )
