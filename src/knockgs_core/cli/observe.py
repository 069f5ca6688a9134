"""``knockgs observe``: RGB-D frames -> tracked points without identity.

``knockgs observe rgbd`` renders a rollout as an RGB-D sequence (``.npz``: colour, coverage,
expected depth, the camera's intrinsics and pose, the frame interval), the format a calibrated
RGB-D capture is stored in too. ``knockgs observe tracks`` follows frame-0 features through
such a sequence by optical flow (by default a sparse pyramidal Lucas-Kanade anchored on frame
0), lifts them to 3-D by the depth and writes them in the tracked-points format that
``knockgs discrepancy run`` reads (``frame, track, x, y, z``, no particle identity;
docs/ladder.md), with the tracker's estimate of its own error per coordinate in the metadata
(``tracker_error_std`` [m]), which the loop takes as its noise unless ``--noise-std`` declares
one (docs/discrepancy.md, "Video observations: the tracker's error"). ``knockgs observe describe`` computes their query
descriptors for ``knockgs calibrate --queries``, to be used with a library described through
the same observation (the observation ladder's ``flow`` tables).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from ..errors import InputError
from ._common import image_side, nonnegative_float, nonnegative_int, positive_float, positive_int

__all__ = ["register", "run_rgbd", "run_tracks", "run_describe", "TRACKS_SETTINGS"]

#: the tracker settings of ``knockgs observe tracks`` (its defaults; the rest is
#: :class:`knockgs_core.observe.TrackSettings`')
TRACKS_SETTINGS = {"method": "lk", "radius": 7}


def register(sub) -> None:
    p = sub.add_parser("observe", help="RGB-D frames of a rollout, and ID-free tracks from RGB-D frames",
                       description=__doc__.splitlines()[0])
    s = p.add_subparsers(dest="observe_command", required=True)
    rg = s.add_parser("rgbd", help="render a rollout as an RGB-D sequence (.npz) with the object's camera")
    rg.add_argument("--asset", required=True, help="the asset's normalized 3DGS PLY (knockgs asset make --normalized)")
    rg.add_argument("--rollout", required=True, help="a rollout .parquet (knockgs simulate ... --export-F)")
    rg.add_argument("--deformation", help="its deformation gradients (default: R.F.parquet next to R.parquet)")
    rg.add_argument("--scene", help="the asset's scene file (default: <asset>.scene.npz next to the PLY)")
    rg.add_argument("--object", required=True, help="object whose contract camera is used")
    rg.add_argument("--profile", default="default", help="resolution profile of the contract (ci, default, paper)")
    rg.add_argument("--width", type=image_side, help="image width in pixels (default: the contract camera's)")
    rg.add_argument("--height", type=image_side, help="image height in pixels (default: the contract camera's)")
    rg.add_argument("--device", default="cpu", help="Warp device (cpu; cuda: a GPU no other process holds; cuda:0)")
    rg.add_argument("--config-dir", help="folder holding objects/ (default: the project's config/)")
    rg.add_argument("-o", "--output", required=True, help="output .npz")
    rg.set_defaults(func=run_rgbd)
    tr = s.add_parser("tracks", help="optical-flow tracks of an RGB-D sequence, lifted by its depth")
    tr.add_argument("frames", help="an RGB-D sequence .npz (knockgs observe rgbd, or a capture in the same format)")
    tr.add_argument("--object", help="object of the measurement's metadata")
    tr.add_argument("--profile", help="profile of the measurement's metadata")
    tr.add_argument("--probe", help="probe of the measurement's metadata (the frames are its export frames 0, 1, ...)")
    tr.add_argument("--method", choices=("lk", "ilk", "tvl1"), default=TRACKS_SETTINGS["method"],
                    help="lk (default): sparse pyramidal Lucas-Kanade against frame 0, sub-pixel; ilk, tvl1: dense flow "
                         "between consecutive frames (scikit-image)")
    tr.add_argument("--max-seeds", type=positive_int, default=400, help="frame-0 corners tracked at most (default 400)")
    tr.add_argument("--radius", type=positive_int, default=TRACKS_SETTINGS["radius"],
                    help=f"Lucas-Kanade window radius in pixels, > 0 (default {TRACKS_SETTINGS['radius']})")
    tr.add_argument("--fb-max", type=positive_float,
                    help="lk: forward-backward tolerance in pixels; a track beyond it is dropped "
                         "(default: TrackSettings.fb_max, 0.3)")
    tr.add_argument("--depth-noise", type=nonnegative_float, default=0.0, help="Gaussian depth noise std added [m] (default 0)")
    tr.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the depth noise, >= 0")
    tr.add_argument("--noise-std", type=float, help="declare the tracks' noise std per coordinate [m] (metadata noise_std; "
                    "default: none, the loop then uses the tracker's error estimate)")
    tr.add_argument("-o", "--output", required=True, help="output tracked points (.parquet, .csv or .npz)")
    tr.set_defaults(func=run_tracks)
    de = s.add_parser("describe", help="query descriptors (a CSV for `knockgs calibrate --queries`) of tracked points")
    de.add_argument("tracks", nargs="+", metavar="[NAME=]FILE", help="tracked points (.parquet, .csv, .npz); NAME: the "
                    "query's case name (default: the file's stem)")
    de.add_argument("-o", "--output", required=True, help="output query CSV (case_name + the five descriptor columns)")
    de.set_defaults(func=run_describe)


def run_rgbd(args) -> int:
    from ..io import check_outputs
    from .._warp import warp_device
    from ..contract import load_contract
    from ..render import camera_from_contract
    from ..observe import render_rgbd, write_rgbd
    from ._common import contract_inputs
    from .render import _check_inputs, _load, _paths

    if not str(args.output).endswith(".npz"):
        raise InputError(str(args.output), "--output", "an RGB-D sequence is written as .npz")
    paths = _paths(args)
    _check_inputs(args, paths)
    contract = load_contract(args.object, args.profile, config_dir=args.config_dir)
    check_outputs({"--output": args.output}, {**paths, **contract_inputs(contract)})
    warp_device(args.device)
    gaussians, gaussian_index, static_mask, ro, F = _load(args, paths, contract)
    camera = camera_from_contract(contract.camera, width=args.width, height=args.height)
    frame_dt = float(ro.meta["probe"]["export"]["frame_dt"])
    frames = render_rgbd(gaussians, static_mask, gaussian_index, ro.positions, F, camera, frame_dt=frame_dt,
                         device=args.device)
    write_rgbd(args.output, frames)
    print(f"{frames.n_frames} RGB-D frames {camera.width}x{camera.height} -> {args.output}", file=sys.stderr)
    return 0


def run_tracks(args) -> int:
    import numpy as np

    from ..io import check_outputs
    from ..discrepancy import Measurement, write_measured
    from ..observe import TrackSettings, read_rgbd, track_points
    from ._common import check_command_inputs

    out = Path(args.output)
    if out.suffix.lower() not in (".parquet", ".csv", ".npz"):
        raise InputError(str(out), "--output", "tracked points are written as .parquet, .csv or .npz")
    check_command_inputs(args, {"frames": args.frames})
    if args.probe and not args.object:
        raise InputError("command line", "--probe", "needs --object (and --profile): the probe is checked against "
                         "the object's contract before it is written to the metadata")
    check_outputs({"--output": out}, {"frames": args.frames})
    frames = read_rgbd(args.frames)
    if args.noise_std is not None and not (math.isfinite(args.noise_std) and args.noise_std >= 0):
        raise InputError("command line", "--noise-std", f"must be a finite number >= 0 [m], got {args.noise_std!r}")
    settings = TrackSettings(method=args.method, max_seeds=args.max_seeds, radius=args.radius, depth_noise=args.depth_noise,
                             seed=args.seed, **({} if args.fb_max is None else {"fb_max": args.fb_max}))
    points, info = track_points(frames, settings)
    meta = {k: v for k, v in (("object", args.object), ("profile", args.profile), ("probe", args.probe)) if v}
    meta["tracker_error_std"] = info["error_std"]
    if args.noise_std is not None:
        meta["noise_std"] = float(args.noise_std)
    if args.probe and args.object:
        from ..contract import load_contract

        probe = load_contract(args.object, args.profile or "default").probes.get(args.probe)
        if probe is None:
            raise InputError(args.frames, "--probe", f"the contract of '{args.object}' has no probe '{args.probe}'")
        if abs(probe.export.frame_dt - frames.frame_dt) > 1e-9 * probe.export.frame_dt:
            raise InputError(args.frames, "frame_dt", f"{frames.frame_dt} s between frames, but probe '{args.probe}' "
                             f"exports every {probe.export.frame_dt} s")
    meta["description"] = (f"optical-flow tracks ({info['method']}) lifted by depth from {Path(args.frames).name}: "
                           f"{info['tracks']} of {info['seeds']} seeds, depth noise {args.depth_noise:g} m, "
                           f"estimated error {info['error_std']:.3g} m per coordinate")
    m = Measurement(points=points, frames=np.arange(frames.n_frames), times=None, particle=None,
                    track=np.arange(1, points.shape[1] + 1), meta=meta, source=str(out))
    write_measured(out, m)
    noise = (f"noise std {args.noise_std:g} m declared (--noise-std)" if args.noise_std is not None else
             "the loop's noise: this estimate (no --noise-std)")
    print(f"{info['tracks']} tracks of {info['seeds']} seeds over {frames.n_frames} frames "
          f"(median flow {info['median_flow_px']:.3g} px); tracker error estimate {info['error_std']:.3g} m per "
          f"coordinate (scatter about an affine motion field); {noise} -> {out}", file=sys.stderr)
    return 0


def run_describe(args) -> int:
    import pandas as pd

    from ..io import check_outputs, write_text
    from ..descriptors import FEATURE_NAMES, descriptor
    from ..discrepancy import read_measured

    named = []
    for item in args.tracks:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).stem, item
        if not name:
            raise InputError(item, "tracks", "empty case name before '='")
        named.append((name, path))
    if len({n for n, _ in named}) != len(named):
        raise InputError("tracks", "case_name", "case names must be unique (use NAME=FILE)")
    from ._common import check_command_inputs

    check_command_inputs(args, {f"tracks {n}": p for n, p in named})
    check_outputs({"--output": args.output}, {f"tracks {n}": p for n, p in named})
    rows, frames = [], set()
    for name, path in named:
        m = read_measured(path)
        frames.add(m.n_frames)
        rows.append({"case_name": name, **dict(zip(FEATURE_NAMES, descriptor(m.points, n_frames=None, source=path)))})
    if len(frames) > 1:
        raise InputError("tracks", "frame", f"the files have different frame counts {sorted(frames)}")
    write_text(args.output, pd.DataFrame(rows).to_csv(index=False, float_format="%.10g", lineterminator="\n"))
    print(f"{len(rows)} query descriptor(s) -> {args.output}", file=sys.stderr)
    return 0
