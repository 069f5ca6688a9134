"""The MPM at some levels against the floor study's kept reference and its check, apart: the
points near the pushed patch and far from it (0.25 m from the probe box's centre), the mean
displacement, and the RMS amplitude over the reference's (CPU; the reference read from the
floor study's cache, the MPM rerun: a minute or two per level at n_grid 32-64).

    python3 benchmarks/floor_amplitude.py --object vasedeck --solid --snap-supports 16 --levels 32 64 \
        --fem-n-grid 64 --fem-check-n-grid 48 --fem-body level_set --body-resolution 128 --reference-cache fem_cache
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from _floor_object import add_object_arguments, add_reference_arguments, floor_object, reference_settings



def main() -> None:
    from knockgs_core.assets import build_asset
    from knockgs_core.experiments import at_resolution
    from knockgs_core.experiments._floor import _fem_run, _reference_runs
    from knockgs_core.rollout import run_rollouts

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_object_arguments(ap, default_object="vasedeck")
    add_reference_arguments(ap)
    ap.add_argument("--fem-body", default="level_set", choices=("voxel", "level_set"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reference-cache", type=Path, required=True)
    args = ap.parse_args()
    contract, s = floor_object(args)
    s = reference_settings(args, s, fem_body=args.fem_body, fem_body_resolution=args.body_resolution)
    gs = build_asset(contract).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)
    probe = contract.roles["calibration"]
    pr = contract.probes[probe]
    n_rec = int(pr.export.n_frames)
    fem = {name: _fem_run(c, ps, points, world, (1.0, 1.0), probe, cache=args.reference_cache)["u"][:n_rec]
           for name, (c, ps, world) in _reference_runs(contract, s).items()}
    ref = fem["fem (reference)"]
    far = np.linalg.norm(points - np.asarray(pr.box.center), axis=1) > 0.25 if pr.box is not None else np.ones(len(points), bool)
    runs = {"fem (check)": fem["fem (check)"]}
    for n in args.levels:
        c = at_resolution(contract, n)
        ro = run_rollouts(c, [((1.0, 1.0), probe)], particles=build_asset(c).particles, device=args.device)[0]
        X = np.asarray(ro.positions, dtype=np.float64)[:, : len(points)]
        runs[f"mpm {n}"] = X - X[0]
    for name, u in runs.items():
        gap = lambda m: 100 * np.linalg.norm(u[:, m] - ref[:, m]) / np.linalg.norm(ref[:, m])  # noqa: E731
        amp = lambda m: np.linalg.norm(u[:, m]) / np.linalg.norm(ref[:, m])  # noqa: E731
        mean = 100 * np.linalg.norm(u.mean(1) - ref.mean(1)) / np.linalg.norm(ref.mean(1))
        print(f"{name}: trajectory {gap(slice(None)):.1f} % (near the patch {gap(~far):.1f} %, far {gap(far):.1f} %), "
              f"mean displacement {mean:.1f} %, RMS over the reference's {amp(slice(None)):.3f} "
              f"(near {amp(~far):.3f}, far {amp(far):.3f})", flush=True)


if __name__ == "__main__":
    main()
