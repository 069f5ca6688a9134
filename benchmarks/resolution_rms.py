"""How much the Probe-A response of one theta depends on the spatial resolution.

Two measurements of the RMS-displacement curve of the Gaussian-associated particles (all
exported frames), relative L2 differences in % of the finer curve:

- ``profiles``: the same theta simulated by two resolution profiles of one contract (each
  with its own Gaussians, fill, grid and substep: two discretizations of the object);
- ``refine``: the profile's Gaussians fixed, fill and grid refined together (n_grid x 1, 1.5,
  2, the convergence study's ``n_grid+fill`` levels at one substep within the finest grid's CFL
  bound), objects with an interior fill only.

    python3 benchmarks/resolution_rms.py --object pillow --profiles ci default --refine default
"""

from __future__ import annotations

import argparse

import numpy as np

THETAS = ((0.60, 1.65), (0.95, 1.35), (1.15, 0.75))


def rms_curve(positions: np.ndarray, n_gs: int) -> np.ndarray:
    """RMS displacement [m] per frame of the first ``n_gs`` particles (the Gaussian-associated
    ones), shape (frames,): :func:`knockgs_core.metrics.rms_displacement_curve`."""
    from knockgs_core.metrics import rms_displacement_curve

    return rms_displacement_curve(np.asarray(positions[:, :n_gs], dtype=np.float64))


def change(a: np.ndarray, b: np.ndarray) -> float:
    """Relative L2 difference of two curves, in % of ``b``."""
    return float(np.linalg.norm(a - b) / np.linalg.norm(b) * 100.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profiles", nargs=2, default=None, metavar=("COARSE", "FINE"))
    ap.add_argument("--refine", default=None, metavar="PROFILE")
    args = ap.parse_args()

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments._convergence import SPACE_FACTORS, _fixed_volumes, _space_dt, refined_particles
    from knockgs_core.rollout import run_rollout

    if args.profiles:
        curves = {}
        for profile in args.profiles:
            c = load_contract(args.object, profile)
            ps = build_asset(c).particles
            for theta in THETAS:
                curves[profile, theta] = rms_curve(run_rollout(c, theta, c.roles["calibration"], particles=ps).positions, ps.n_gs)
        coarse, fine = args.profiles
        for theta in THETAS:
            a, b = curves[coarse, theta], curves[fine, theta]
            print(f"{args.object} theta {theta}: {coarse} vs {fine} RMS curve {change(a, b):.1f} %, "
                  f"peak {a.max() * 1e3:.2f} vs {b.max() * 1e3:.2f} mm", flush=True)
    if args.refine:
        c = load_contract(args.object, args.refine)
        ps = build_asset(c).particles
        probe = c.roles["calibration"]
        grids = [int(round(c.sim.n_grid * f)) for f in SPACE_FACTORS]
        dt = _space_dt(c, grids[-1], c.probes[probe].export.frame_dt)
        curves = {}
        for n, f in zip(grids, SPACE_FACTORS):
            variant, particles = (c, _fixed_volumes(c, ps)) if f == 1.0 else \
                refined_particles(c, ps, n_grid=n, fill_resolution=int(round(c.fill.resolution * f)))
            for theta in THETAS:
                ro = run_rollout(variant, theta, probe, particles=particles, sim_overrides={"dt": dt, "n_grid": n})
                curves[n, theta] = rms_curve(ro.positions, ps.n_gs)
        for theta in THETAS:
            a, b, d = (curves[n, theta] for n in grids)
            ref = np.linalg.norm(d)   # both changes in % of the finest curve
            print(f"{args.object} theta {theta}: n_grid {grids[0]} -> {grids[1]} {np.linalg.norm(a - b) / ref * 100:.1f} %, "
                  f"{grids[1]} -> {grids[2]} {np.linalg.norm(b - d) / ref * 100:.1f} % (dt {dt:g} s)", flush=True)


if __name__ == "__main__":
    main()
