"""A finer-grid world seen only through rendered RGB-D video (issue 57, part 5): is it analysed
like the same world observed as tracks?

The discrepancy suite's finer world (``discrepancy.world_cases``: the MPM at twice the loop's
grid with the neighbouring finer profile's Gaussians and fill, a planted catalogue effect whose
strength is searched for a 25 % held-out change) is made once as the suite makes it
(``make_world_case``: tracks without identity of 60 % of its Gaussians, 2 % noise). The same
world, at the searched strength, is then filmed: its Gaussians rendered with their deformation
gradients by the contract's camera (``observe.render_rgbd``, ``--size``), under the calibration
and the held-out probe, and ``knockgs observe tracks`` turns each video into tracks without
identity with its own error estimate (``tracker_error_std``, which the loop takes as its noise).
The loop (``run_discrepancy``, default settings and catalogue, on ``--device``) runs on the
tracks and on the video, each scored against the world's truth (``evaluate_case``,
``world_acceptance``).

    python3 benchmarks/video_world.py --case finer_damping --size 200x150 --out OUT --jobs 2

Resumable: a finished file is read back. Writes ``OUT/video_world_{case}.csv|md``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pandas as pd

from knockgs_core.io import write_json, write_npz, write_text

from _world_loop import run_and_score

PROFILE = "ci"


def _loop_contract(obj):
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    c = load_contract(obj, PROFILE)
    return c, build_asset(c).particles


def tracks_case(args) -> Path:
    """The world case as the suite makes it (tracks), in OUT/tracks."""
    from knockgs_core.discrepancy import make_world_case, world_cases

    folder = args.out / "tracks"
    if (folder / "truth.json").is_file():
        return folder
    c, particles = _loop_contract(args.object)
    spec = next(s for s in world_cases() if s.name == args.case)
    folder.mkdir(parents=True, exist_ok=True)
    make_world_case(spec, c, particles, measured_dir=folder, truth_dir=folder, calibration_probe=c.roles["calibration"],
                    heldout_probe=c.roles["heldout"][0], device=args.device)
    return folder


def video_case(args, tracks: Path) -> Path:
    """The same world at the searched strength, filmed and tracked, in OUT/video (the truth's
    clean motion copied from the tracks case)."""
    import numpy as np

    from knockgs_core.assets import build_asset
    from knockgs_core.cli import main as cli_main
    from knockgs_core.discrepancy import finer_world_rollout, world_contract
    from knockgs_core.observe import render_rgbd, write_rgbd
    from knockgs_core.render import camera_from_contract

    folder = args.out / "video"
    if (folder / "truth.json").is_file():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    truth = json.loads((tracks / "truth.json").read_text())
    c, _ = _loop_contract(args.object)
    wc = world_contract(c)
    world = build_asset(wc)
    H = c.probes[truth["calibration_probe"]].export.horizon
    width, height = (int(v) for v in args.size.split("x"))
    cam = camera_from_contract(c.camera, width=width, height=height)
    files, errors = {}, {}
    for role, probe in (("calib", truth["calibration_probe"]), ("heldout", truth["heldout_probe"])):
        # the searched strength (None: no effect)
        ro = finer_world_rollout(wc, world.particles, tuple(truth["theta_true"]), probe, planted=truth["planted_effect"],
                                 strength=truth["strength"], horizon=H, device=args.device, export_F=True)
        video = folder / f"{role}.rgbd.npz"
        write_rgbd(video, render_rgbd(world.gaussians, np.asarray(world.static_mask), np.asarray(world.particles.gaussian_index),
                                      np.asarray(ro.positions), np.asarray(ro.F), cam, frame_dt=wc.probes[probe].export.frame_dt))
        out = folder / f"measured_{role}.parquet"
        if cli_main(["observe", "tracks", str(video), "--object", args.object, "--profile", PROFILE, "--probe", probe,
                     "-o", str(out)]) != 0:
            raise SystemExit(f"observe tracks failed on {video}")
        files[role] = str(out)
        from knockgs_core.discrepancy import read_measured

        errors[role] = read_measured(out).meta.get("tracker_error_std")
    with np.load(tracks / "clean.npz") as z:  # the truth's motion, written atomically as every file here
        write_npz(folder / "clean.npz", **{k: z[k] for k in z.files})
    write_json(folder / "truth.json", {**truth, "observation": f"video {args.size}, knockgs observe tracks",
                                       "measured_files": files, "tracker_error_std": errors})
    return folder


def _loop(job):
    args, case_dir = job
    out = Path(case_dir) / "run"
    if (out / "row.json").is_file():
        return json.loads((out / "row.json").read_text())
    c, particles = _loop_contract(args.object)
    row, result = run_and_score(case_dir, out, c, particles, device=args.device)
    row.update({"observation": Path(case_dir).name, "noise_std": result["noise"]["std"], "verdict": result["verdict"]})
    write_json(out / "row.json", row)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--case", default="finer_damping")
    ap.add_argument("--size", default="200x150", help="the video's width x height in pixels")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    t0 = time.perf_counter()
    tracks = tracks_case(args)
    video = video_case(args, tracks)
    print(f"worlds made in {time.perf_counter() - t0:.0f} s", flush=True)
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        rows = list(pool.map(_loop, [(args, str(tracks)), (args, str(video))]))
    table = pd.DataFrame(rows)
    cols = ["observation", "points", "noise_std", "theta_true", "theta_before", "theta_after", "theta_error_after_pct",
            "theta_interval", "theta_in_interval", "identified_effect", "verdict_kind", "heldout_change",
            "heldout_traj_rmse_before", "heldout_traj_rmse_after", "heldout_improvement", "accepted", "n_simulations", "seconds"]
    table = table[[k for k in cols if k in table.columns] + ["verdict"]]
    write_text(args.out / f"video_world_{args.case}.csv", table.to_csv(index=False))
    write_text(args.out / f"video_world_{args.case}.md", table.drop(columns=["verdict"]).to_markdown(index=False) + "\n\n"
               + "\n".join(f"- {r.observation}: {r.verdict}" for r in table.itertuples()) + "\n")
    print(table.drop(columns=["verdict"]).to_string())


if __name__ == "__main__":
    main()
