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

from knockgs_core.fem._mesh import Region
from knockgs_core.fem._verification import (VerificationSettings, _at, fem_block_reference, mpm_block_model,
                                            response_gap)
from knockgs_core.sim import make_state, simulate

PATCH = Region((0.75, 0.75, 1.0), (1.0, 0.875, 1.25))


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
    settings = VerificationSettings(n_grid=(16, 32), frame_dt=args.frame_dt, n_frames=args.n_frames, fem_dt=args.frame_dt / 8)
    knocked = PATCH if args.knock == "patch" else None
    fems = {}
    for cells in args.fem_cells:
        fems[cells] = fem_block_reference(settings, cells=cells, knocked=knocked)
        print(f"FEM P2, {cells} cells per 0.5 m: {fems[cells]['system'].n_dofs} DOFs, {fems[cells]['cpu_s']:.0f} CPU s",
              flush=True)
    for n in args.levels:
        cpu = time.process_time()
        model, x = mpm_block_model(n, settings, device="cpu", knocked=knocked, transfer=args.transfer)
        out = simulate(model, make_state(model, x), frame_dt=settings.frame_dt, n_frames=settings.n_frames)
        u = out.positions.astype(np.float64) - x[None].astype(np.float32).astype(np.float64)
        parts = []
        for cells, fem in fems.items():
            g = response_gap(settings.times, u, _at(fem, x))
            parts.append(f"vs FEM {cells}: RMSE {g['traj_rmse_pct']:.1f} %, period {g['period_error_pct']:+.1f} %, "
                         f"peak {g['peak_error_pct']:+.1f} %")
        print(f"MPM {args.transfer}, {args.knock}, n_grid {n}: impulse {model.probe_impulse[0]:.4g} N s, "
              f"{time.process_time() - cpu:.0f} CPU s | " + " | ".join(parts), flush=True)
    finest = fems[args.fem_cells[-1]]
    ref = _at(finest, x)
    for cells, fem in list(fems.items())[:-1]:
        g = response_gap(settings.times, _at(fem, x), ref)
        print(f"FEM {cells} vs FEM {args.fem_cells[-1]}: RMSE {g['traj_rmse_pct']:.2f} %, period {g['period_error_pct']:+.2f} %")


if __name__ == "__main__":
    main()
