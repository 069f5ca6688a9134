"""The verification block knocked on a patch instead of everywhere: does the MPM's trajectory
converge to the finite-element reference's under a local impulse, as under a uniform one?
(CPU, about 1 minute for the whole block at the default levels; the patch's reference on 12
cells per 0.5 m is some 5 minutes.)

The problem is :mod:`knockgs_core.fem._verification`'s (the block 0.5 x 0.5 x 0.75 m held by its
bottom 0.25 m, E = 1.15e4 Pa, rho = 1500 kg/m^3, a pulse of 1e-4 s giving 2 mm/s per unit mass
along x), with the pulse either on the whole block (``--knock whole``: the verification table's)
or on a patch of its top's -y side, ``[0.75, 1.0] x [0.75, 0.875] x [1.0, 1.25]`` m (``--knock
patch``: a contact probe's kind of knock, bending and twisting the block; its faces on the grid
planes of every level here and on the FEM's mesh planes). The MPM is the simulator at each level
of ``--levels`` with ``--transfer``; the FEM is P2, Newmark at 8 steps a frame, on each mesh of
``--fem-cells`` (cells per 0.5 m), the finest the reference. Printed: each MPM level's trajectory
RMSE (% of the reference's RMS displacement), first-mode period and peak RMS displacement against
every mesh, and the coarser meshes against the finest.

    python3 benchmarks/patch_verification.py --knock patch --levels 16 32 48 --fem-cells 6 12
    python3 benchmarks/patch_verification.py --knock whole --levels 16 32 48 --fem-cells 6 8
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from knockgs_core.fem import ForcePulse, newmark
from knockgs_core.fem._elasticity import assemble_elasticity, interpolation_matrix, support_dofs
from knockgs_core.fem._mesh import Region, tensor_mesh
from knockgs_core.fem._verification import (BLOCK, GRID_LIM, MATERIAL, PROBE_DURATION, SUPPORT, SUPPORT_TOP,
                                            VerificationSettings, block_particles, mpm_dt, response_gap)
from knockgs_core.sim import Box, FixedCuboid, Probe, SimParams, build_model, make_state, simulate

PATCH = ((0.75, 0.75, 1.0), (1.0, 0.875, 1.25))
IMPULSE_VELOCITY = 0.002   # [m/s] per unit mass, the verification's


def fem_run(cells: int, settings: VerificationSettings, patch: bool):
    """(system, Newmark result, CPU s) of the block on ``cells`` per 0.5 m, P2."""
    (x0, y0, z0), (x1, y1, z1) = BLOCK
    per_m = cells / 0.5
    axis = lambda a, b: np.linspace(a, b, max(1, round((b - a) * per_m)) + 1)  # noqa: E731
    cpu = time.process_time()
    system = assemble_elasticity(tensor_mesh(axis(x0, x1), axis(y0, y1), np.concatenate([[z0], axis(SUPPORT_TOP, z1)])),
                                 **MATERIAL, degree=2)
    fixed = support_dofs(system, Region.from_center(SUPPORT.center, SUPPORT.half_size))
    pulse = ForcePulse((MATERIAL["rho"] * IMPULSE_VELOCITY / PROBE_DURATION, 0.0, 0.0), PROBE_DURATION,
                       region=Region(*PATCH) if patch else None)
    res = newmark(system, dt=settings.frame_dt / 8, frame_dt=settings.frame_dt, n_frames=settings.n_frames,
                  fixed=fixed, pulses=[pulse])
    return system, res, time.process_time() - cpu


def mpm_run(n_grid: int, settings: VerificationSettings, patch: bool, transfer: str):
    """(rest positions [n, 3], displacements [T, n, 3], impulse [N s], CPU s) at ``n_grid``."""
    x = block_particles(n_grid, 2)
    m_p = MATERIAL["rho"] * (GRID_LIM / n_grid) ** 3 / 8
    box = (Box(center=tuple((a + b) / 2 for a, b in zip(*PATCH)),
               half_size=tuple((b - a) / 2 + 1e-6 for a, b in zip(*PATCH))) if patch else None)
    probe = Probe("knock", force=(m_p * IMPULSE_VELOCITY / PROBE_DURATION, 0.0, 0.0), box=box, n_steps=1,
                  dt_ref=PROBE_DURATION)
    params = SimParams(n_grid=n_grid, grid_lim=GRID_LIM, dt=mpm_dt(n_grid, settings), boundaries=(FixedCuboid(SUPPORT),),
                       transfer=transfer)
    cpu = time.process_time()
    model = build_model(x, **MATERIAL, params=params, probe=probe, device="cpu")
    out = simulate(model, make_state(model, x), frame_dt=settings.frame_dt, n_frames=settings.n_frames)
    u = out.positions.astype(np.float64) - x[None].astype(np.float32).astype(np.float64)
    return x, u, float(model.probe_impulse[0]), time.process_time() - cpu


def at_points(system, res, x: np.ndarray) -> np.ndarray:
    P = interpolation_matrix(system, x)
    return (P @ res.u.T).reshape(3, len(x), -1).transpose(2, 1, 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--knock", choices=("patch", "whole"), default="patch")
    ap.add_argument("--levels", type=int, nargs="+", default=[16, 32, 48],
                    help="MPM grids (the patch's faces need multiples of 16)")
    ap.add_argument("--fem-cells", type=int, nargs="+", default=[6, 12], help="FEM cells per 0.5 m, the last the reference")
    ap.add_argument("--transfer", choices=("affine_flip", "apic"), default="affine_flip")
    ap.add_argument("--frame-dt", type=float, default=0.05)
    ap.add_argument("--n-frames", type=int, default=41)
    args = ap.parse_args()
    if args.knock == "patch" and any(n % 16 for n in args.levels):
        ap.error("--knock patch: levels must be multiples of 16 (the patch's faces on grid planes)")
    settings = VerificationSettings(n_grid=(16, 32), frame_dt=args.frame_dt, n_frames=args.n_frames)
    patch = args.knock == "patch"
    fems = {}
    for cells in args.fem_cells:
        system, res, cpu = fem_run(cells, settings, patch)
        fems[cells] = (system, res)
        print(f"FEM P2, {cells} cells per 0.5 m: {system.n_dofs} DOFs, {cpu:.0f} CPU s", flush=True)
    finest = args.fem_cells[-1]
    for n in args.levels:
        x, u, impulse, cpu = mpm_run(n, settings, patch, args.transfer)
        parts = []
        for cells, (system, res) in fems.items():
            g = response_gap(settings.times, u, at_points(system, res, x))
            parts.append(f"vs FEM {cells}: RMSE {g['traj_rmse_pct']:.1f} %, period {g['period_error_pct']:+.1f} %, "
                         f"peak {g['peak_error_pct']:+.1f} %")
        print(f"MPM {args.transfer}, {args.knock}, n_grid {n}: impulse {impulse:.4g} N s, {cpu:.0f} CPU s | " + " | ".join(parts),
              flush=True)
    x = block_particles(args.levels[-1], 2)
    ref = at_points(*fems[finest], x)
    for cells, (system, res) in list(fems.items())[:-1]:
        g = response_gap(settings.times, at_points(system, res, x), ref)
        print(f"FEM {cells} vs FEM {finest}: RMSE {g['traj_rmse_pct']:.2f} %, period {g['period_error_pct']:+.2f} %")


if __name__ == "__main__":
    main()
