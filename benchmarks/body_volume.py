"""The volume of an object's body as the fill measures it (``fill_grid`` and ``body_fraction``,
the ``enclosed`` rule's body) at fill resolutions of one's choosing: does the body stay the same
when the fill grid is finer than the Gaussians sample the surface?

    python3 benchmarks/body_volume.py --object pillow --profiles default paper --resolutions 32 48 64 96 128 192 256

Prints, for each profile's simulated Gaussians, their sampling spacing (``sampling_spacing``)
and, at each resolution, the cell size, the shell's cells, the body's volume [m^3] and the
seconds it took. The paper profile's Gaussians (about half a million on the Pillow) sample the
surface at 1.4 mm: their body is the reference for the coarser profiles'.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def simulated_gaussians(contract):
    """The Gaussians ``build_asset`` simulates (preprocessed, static supports removed)."""
    from knockgs_core.assets._build import load_source_gaussians, preprocess

    a = contract.asset
    gs, _ = preprocess(load_source_gaussians(contract), opacity_threshold=a.opacity_threshold, rotations=a.rotations,
                       crop=a.crop, source=contract.source, field_prefix="asset.")
    static = np.zeros(len(gs), dtype=bool)
    for box in a.static_boxes:
        static |= box.contains(gs.means)
    return gs.subset(np.flatnonzero(~static))


def main() -> None:
    from knockgs_core.assets import body_fraction, fill_grid
    from knockgs_core.assets._fill import sampling_spacing
    from knockgs_core.contract import load_contract

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profiles", nargs="+", default=["default"])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[32, 48, 64, 96, 128])
    args = ap.parse_args()
    print("| profile | Gaussians | spacing [m] | fill n | h [m] | shell cells | body [m^3] | s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for profile in args.profiles:
        c = load_contract(args.object, profile)
        if c.fill.box is None:
            raise SystemExit(f"{args.object} at {profile} has no fill box")
        gs = simulated_gaussians(c)
        s = sampling_spacing(gs.means)
        for n in args.resolutions:
            t0 = time.perf_counter()
            grid = fill_grid(gs, fill_box=c.fill.box, resolution=n, density_threshold=c.fill.density_threshold)
            vol = float(body_fraction(grid, gs.means).sum()) * float(np.prod(grid.h))
            print(f"| {profile} | {len(gs):,} | {s:.4f} | {n} | {grid.h[0]:.4f} | {int(grid.shell.sum()):,} | {vol:.4f} | "
                  f"{time.perf_counter() - t0:.1f} |", flush=True)


if __name__ == "__main__":
    main()
