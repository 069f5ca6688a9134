"""How much of an object's floor is its rim: the MPM levels of the floor study with the particles
above a height carrying their rule's volume, and again carrying next to none (CPU, minutes).

A solid body's open rim (the Vasedeck's flared lip above its closed mouth) is a sheet of
Gaussians thinner than the fill's cells: the ``enclosed`` rule gives it a volume that depends on
the fill grid (the shell band's ramp), while the finite-element reference, meshed to the level
set the fill encloses, keeps almost none of it. Here the particles with rest height above
``--rim-above`` [m] get ``--rim-share`` of the median particle's volume in the second run
(the others scaled so that the total is unchanged): the MPM with a massless rim, as the
reference has it. Each level is compared with the floor study's reference (computed, or read
from ``--reference-cache`` where ``floor_levels.py`` kept it): trajectory RMSE and its slow
band's (% of the reference's RMS displacement), first-mode period over the Probe-A record.

    python3 benchmarks/floor_rim.py --object vasedeck --profile config --solid --snap-supports 16 \
        --levels 48 64 96 --fem-n-grid 64 --fem-check-n-grid 48 --body-resolution 128 \
        --rim-above 1.335 --reference-cache fem_cache --fit-steps 2

``--fit-steps``: also the theta each level needs to match the reference (the floor study's
Gauss-Newton fit from (1, 1), over the record and in the band).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from _floor_object import add_object_arguments, add_reference_arguments, floor_object, reference_settings


def main() -> None:
    from knockgs_core.assets import build_asset
    from knockgs_core.experiments import at_resolution, band_components, band_limited, fit_theta, probe_period
    from knockgs_core.experiments._floor import _fem_run, _reference_runs, level_simulator

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_object_arguments(ap, default_object="vasedeck")
    add_reference_arguments(ap)
    ap.add_argument("--rim-above", type=float, required=True, help="rest height [m] above which a particle is the rim")
    ap.add_argument("--rim-share", type=float, default=1e-4, help="the massless rim's volume, x the median particle's")
    ap.add_argument("--band-hz", type=float, default=5.0)
    ap.add_argument("--fit-steps", type=int, default=0,
                    help="Gauss-Newton steps of the theta a level needs to match the reference (record and band)")
    ap.add_argument("--reference-cache", type=Path, default=None)
    args = ap.parse_args()

    contract, settings = floor_object(args)
    settings = reference_settings(args, settings, record_factor=1)
    probe = contract.roles["calibration"]
    pr = contract.probes[probe]
    gs = build_asset(contract).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)
    ref_contract, ref_particles, world = _reference_runs(contract, settings)["fem (reference)"]
    t0 = time.perf_counter()
    ref = _fem_run(ref_contract, ref_particles, points, world, (1.0, 1.0), probe, cache=args.reference_cache)["u"]
    print(f"reference: n_grid {world.n_grid}, {world.body} body, {time.perf_counter() - t0:.0f} s", flush=True)
    times = np.arange(len(ref)) * float(pr.export.frame_dt)
    band = band_components(args.band_hz, float(pr.export.frame_dt), len(ref))
    direction = np.asarray(pr.force, dtype=np.float64)
    p_ref = probe_period(times, ref, direction)
    rel = lambda a, b: 100.0 * float(np.linalg.norm(a - b) / np.linalg.norm(b))  # noqa: E731

    for n in args.levels:
        c = at_resolution(contract, n)
        built = build_asset(c).particles
        rim = np.asarray(built.positions)[:, 2] > args.rim_above
        vol = np.asarray(built.volumes, dtype=np.float64).copy()
        total = vol.sum()
        vol[rim] = args.rim_share * float(np.median(vol[~rim]))
        vol[~rim] *= (total - vol[rim].sum()) / vol[~rim].sum()        # the same total, the rim's moved to the body
        massless = dataclasses.replace(built, volumes=vol.astype(np.float32))
        for name, particles in (("with its rim", built), ("massless rim", massless)):
            t0 = time.perf_counter()
            simulate = level_simulator(c, particles, probe, len(points))
            u = simulate([(1.0, 1.0)])[0]
            period = probe_period(times, u, direction)
            fits = ""
            if args.fit_steps:
                whole = fit_theta(simulate, ref, steps=args.fit_steps, first=u)["theta"]
                slow = fit_theta(lambda th: [band_limited(x, band) for x in simulate(th)], band_limited(ref, band),
                                 steps=args.fit_steps, first=band_limited(u, band))["theta"]
                fits = f"; theta fit ({whole[0]:.3f}, {whole[1]:.3f}), in the band ({slow[0]:.3f}, {slow[1]:.3f})"
            print(f"MPM n_grid {n}, {name}: rim volume {1e3 * float(np.asarray(particles.volumes)[rim].sum()):.3f} dm^3 of "
                  f"{1e3 * float(np.asarray(particles.volumes).sum()):.2f}; RMSE {rel(u, ref):.1f} %, "
                  f"band <= {args.band_hz:g} Hz {rel(band_limited(u, band), band_limited(ref, band)):.1f} %, "
                  f"period {period:.4f} s ({100 * (period - p_ref) / p_ref:+.1f} % of {p_ref:.4f}){fits}, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
