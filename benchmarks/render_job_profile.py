"""Where one render job's time goes: the workflow's render step for one theta (every
evaluation probe: read the positions, read the deformation gradients, deform and render
every frame, write the compressed frames), timed per stage and profiled with cProfile.

Needs the object's asset and the theta's evaluation rollouts in ``results/<profile>/``
(e.g. ``snakemake results/paper/rollouts/pillow/eval/sE0.800000_sR1.600000
--configfile=config/paper.yaml --resources gpu=1``).

    python3 benchmarks/render_job_profile.py --object pillow --profile paper --theta sE0.800000_sR1.600000 --device cuda:0
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--theta", required=True, help="the evaluation folder's tag, e.g. sE0.800000_sR1.600000")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--per-frame-scene", action="store_true",
                    help="deform and render each frame through the public render(*deformed_scene(...)) "
                         "(every frame's scene checked in full), not render_frames (the rest scene checked once)")
    args = ap.parse_args()

    from knockgs_core.io import write_npz
    from knockgs_core.assets import load_scene, read_ply
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import camera_from_contract, render_rollout
    from knockgs_core.rollout import read_deformation, read_rollout

    root = Path("results") / args.profile
    contract = load_contract(args.object, args.profile)
    gaussians = read_ply(root / "assets" / f"{args.object}.ply")
    static_mask, gaussian_index = load_scene(root / "assets" / f"{args.object}.scene.npz", n_gaussians=len(gaussians))
    cam = camera_from_contract(contract.camera, width=args.width, height=args.height)
    folder = root / "rollouts" / args.object / "eval" / args.theta
    probes = sorted(p.name[: -len(".parquet")] for p in folder.glob("*.parquet") if not p.name.endswith(".F.parquet"))
    stages = {"read positions": 0.0, "read F": 0.0, "deform + render": 0.0, "write frames": 0.0}
    prof = cProfile.Profile()
    with tempfile.TemporaryDirectory() as out:
        t_all = time.perf_counter()
        prof.enable()
        frames = 0
        for probe in probes:
            t = time.perf_counter()
            ro = read_rollout(folder / f"{probe}.parquet")
            stages["read positions"] += time.perf_counter() - t
            t = time.perf_counter()
            F = read_deformation(folder / f"{probe}.F.parquet")
            stages["read F"] += time.perf_counter() - t
            t = time.perf_counter()
            if args.per_frame_scene:
                rgb, alpha = per_frame(gaussians, static_mask, gaussian_index, ro.positions, F, cam, args.device)
            else:
                rgb, alpha = render_rollout(gaussians, static_mask, gaussian_index, ro.positions, F, cam, device=args.device)
            stages["deform + render"] += time.perf_counter() - t
            t = time.perf_counter()
            write_npz(Path(out) / f"{probe}.npz", rgb=rgb.astype(np.float16), alpha=alpha.astype(np.float16))
            stages["write frames"] += time.perf_counter() - t
            frames += len(rgb)
        prof.disable()
        total = time.perf_counter() - t_all
    path = "per-frame deformed_scene + render" if args.per_frame_scene else "render_frames"
    print(f"{args.object} ({args.profile}), {len(gaussians):,} Gaussians, {len(probes)} probes, {frames} frames "
          f"at {args.width}x{args.height} on {args.device}, {path}: {total:.1f} s")
    print("| stage | s | share |")
    print("|---|---:|---:|")
    for k, v in stages.items():
        print(f"| {k} | {v:.2f} | {100 * v / total:.0f} % |")
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.top)
    print(s.getvalue())


def per_frame(gaussians, static_mask, gaussian_index, positions, F, cam, device):
    """Every frame through ``render(*deformed_scene(...))``: the rest scene checked, copied and
    symmetrized in full at each frame."""
    from knockgs_core.render import deformed_scene, render

    means0 = np.asarray(gaussians.means, dtype=np.float64)
    cov0 = np.asarray(gaussians.covariances(), dtype=np.float64)
    colors = np.asarray(gaussians.colors(), dtype=np.float64)
    opac = np.asarray(gaussians.opacities, dtype=np.float64)
    n_gs = len(gaussian_index)
    outs = [render(*deformed_scene(means0, cov0, colors, opac, positions[t, :n_gs], F[t], static_mask), cam, device=device)
            for t in range(positions.shape[0])]
    return np.stack([o.rgb for o in outs]), np.stack([o.alpha for o in outs])


if __name__ == "__main__":
    main()
