"""How much the finite-element reference's response depends on the surface its body is measured
on (CPU, a minute or two per body at n_grid 48-64).

One object, one particle set (the floor study's reference construction at ``--body-n-grid``),
one mesh (``--mesh-n-grid``); the level-set body measured on each fill grid of ``--fills``
(``FemWorld.body_resolution``). Printed per fill: the meshed volume, the first-mode period over
the floor block's record, and the Probe-A trajectory's gap to the last fill's: all points, the
points farther than 0.25 m from the probe box's centre, and the mean displacement.

    python3 benchmarks/reference_bodies.py --object vasedeck --solid --mesh-n-grid 64 --fills 64 128 192 \
        --cache fem_cache
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from _floor_object import add_object_arguments, floor_object


def main() -> None:
    from knockgs_core.assets import build_asset
    from knockgs_core.experiments import at_resolution, probe_period
    from knockgs_core.experiments._floor import _fem_run, _with_record
    from knockgs_core.fem import FemWorld

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_object_arguments(ap, default_object="vasedeck")
    ap.add_argument("--body-n-grid", type=int, default=64)
    ap.add_argument("--mesh-n-grid", type=int, required=True)
    ap.add_argument("--fills", type=int, nargs="+", required=True,
                    help="fill grids the body is measured on; the last is compared with")
    ap.add_argument("--cache", type=Path, default=None)
    args = ap.parse_args()
    base, s = floor_object(args)
    gs = build_asset(base).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)
    probe = base.roles["calibration"]
    pr = base.probes[probe]
    n_rec = int(pr.export.n_frames)
    body = _with_record(at_resolution(base, args.body_n_grid), probe, (n_rec - 1) * int(s.record_factor) + 1)
    particles = build_asset(body).particles
    u = {}
    for r in args.fills:
        world = FemWorld(degree=s.fem_degree, steps_per_frame=s.fem_steps_per_frame, n_grid=args.mesh_n_grid,
                         body="level_set", body_resolution=r)
        run = _fem_run(body, particles, points, world, (1.0, 1.0), probe, cache=args.cache)
        u[r] = run["u"]
        times = np.arange(run["u"].shape[0]) * float(pr.export.frame_dt)
        print(f"fill {r}: volume {run['volume']:.5f} m^3, {run['dofs']} DOFs, period "
              f"{probe_period(times, run['u'], pr.force):.4f} s, {run['cost']:.0f} s", flush=True)
    last = u[args.fills[-1]][:n_rec]
    far = np.linalg.norm(points - np.asarray(pr.box.center), axis=1) > 0.25 if pr.box is not None else np.ones(len(points), bool)
    for r in args.fills[:-1]:
        a = u[r][:n_rec]
        gap = lambda m: 100 * np.linalg.norm(a[:, m] - last[:, m]) / np.linalg.norm(last[:, m])  # noqa: E731
        mean = 100 * np.linalg.norm(a.mean(1) - last.mean(1)) / np.linalg.norm(last.mean(1))
        print(f"fill {r} vs {args.fills[-1]}: trajectory {gap(slice(None)):.1f} %, far from the patch {gap(far):.1f} %, "
              f"mean displacement {mean:.1f} %")


if __name__ == "__main__":
    main()
