"""The error of `knockgs observe tracks` against the rendered truth (CPU, about a minute).

Renders an object's Probe-A rollout (the contract's camera at several image sizes, the
Pillow's ci profile by default) as an RGB-D sequence, tracks it, and compares every track
with where the surface point it started on went (``knockgs_core.observe.surface_truth``: the
frame-0 pixel's point moved by the displacement the renderer blends there). For each image
size and tracker it prints one Markdown row: seeds, the fraction of tracks lost, the true
motion a frame and in all [px], the RMS error per coordinate [m] and per image axis [px], the
error at the last frame [m], the signal (RMS displacement per coordinate [m]), the tracker's
own error estimate (``knockgs_core.observe.tracking_error``) and its ratio to the true error,
and the tracking time.

Trackers: ``ilk (before)``: the tracker as it was (scikit-image's dense iterative
Lucas-Kanade between consecutive frames, radius 5, on the former segmentation: every pixel
the object covers at least half when rendered alone); ``ilk``: the same flow on the
segmentation that leaves out pixels a static support hides (``knockgs_core.observe.render_rgbd``'s
mask); ``lk``: the sparse pyramidal Lucas-Kanade anchored on frame 0 with the settings of
`knockgs observe tracks`.

    python3 benchmarks/tracker_error.py --object pillow --profile ci --sizes 160x120 200x150 400x300 600x450
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


def _size(text: str) -> tuple[int, int]:
    w, _, h = text.partition("x")
    return int(w), int(h)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="ci")
    ap.add_argument("--theta", type=float, nargs=2, default=(1.0, 1.0))
    ap.add_argument("--sizes", type=_size, nargs="+", default=[(160, 120), (200, 150), (400, 300)])
    ap.add_argument("--trackers", nargs="+", default=["ilk (before)", "ilk", "lk"])
    args = ap.parse_args(argv)

    from knockgs_core.assets import build_asset
    from knockgs_core.cli.observe import TRACKS_SETTINGS
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import camera_from_contract
    from knockgs_core.observe import TrackSettings, render_rgbd, surface_truth, track_errors, track_pixels, tracking_error
    from knockgs_core.render import render
    from knockgs_core.rollout import run_rollout

    c = load_contract(args.object, args.profile)
    probe = c.roles["calibration"]
    asset = build_asset(c)
    n_gs = asset.particles.n_gs
    ro = run_rollout(c, tuple(args.theta), probe, particles=asset.particles, export_F=True)
    X, F = np.asarray(ro.positions, np.float64)[:, :n_gs], np.asarray(ro.F, np.float64)
    g, static = asset.gaussians, np.asarray(asset.static_mask)
    frame_dt = float(ro.meta["probe"]["export"]["frame_dt"])
    settings = {"ilk (before)": TrackSettings(method="ilk"), "ilk": TrackSettings(method="ilk"),
                "lk": TrackSettings(**TRACKS_SETTINGS)}
    print(f"{args.object} ({args.profile}), probe {probe}, theta {tuple(args.theta)}, {X.shape[0]} frames; "
          f"lk settings {TRACKS_SETTINGS}\n")
    print("| image | tracker | seeds | lost | motion a frame [px] | motion in all [px] | RMS error [m] | RMS error [px] "
          "| last frame [m] | signal [m] | estimate [m] | estimate / error | time [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for w, h in args.sizes:
        cam = camera_from_contract(c.camera, width=w, height=h)
        frames = render_rgbd(g, static, asset.particles.gaussian_index, X, F, cam, frame_dt=frame_dt)
        dyn = ~static
        alone = render(np.asarray(g.means, np.float64)[dyn], np.asarray(g.covariances(), np.float64)[dyn],
                       np.asarray(g.colors(), np.float64)[dyn], np.asarray(g.opacities, np.float64)[dyn], cam)
        for name in args.trackers:
            fr = dataclasses.replace(frames, mask=alone.alpha >= 0.5) if name == "ilk (before)" else frames
            t0 = time.perf_counter()
            tracks = track_pixels(fr, settings[name])
            dt = time.perf_counter() - t0
            points = tracks.to_world()
            truth = surface_truth(g, static, X, F, cam, tracks.rows[0], tracks.cols[0], tracks.depth[0])
            e = track_errors(cam, tracks.rows, tracks.cols, points, truth)
            est = tracking_error(points)
            lost = 1.0 - tracks.info["tracks"] / tracks.info["seeds"]
            print(f"| {w}x{h} | {name} | {tracks.info['seeds']} | {lost:.0%} | {e.motion_px:.3f} | {e.total_motion_px:.2f} "
                  f"| {e.rms_m:.3g} | {e.rms_px:.3f} | {e.final_rms_m:.3g} | {e.signal_m:.3g} | {est:.3g} "
                  f"| {est / e.rms_m:.2f} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    main()
