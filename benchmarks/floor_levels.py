"""The floor study (``knockgs_core.experiments.floor_study``) at levels of one's choosing: the
MPM on the given device (finer levels on a GPU), the finite-element reference on this
machine's CPU. Writes the table as CSV and Markdown under ``--out``.

    python3 benchmarks/floor_levels.py --object pillow --profile config --volumes enclosed \
        --levels 32 48 64 96 128 --fem-n-grid 48 --fem-check-n-grid 32 --device cuda:0 --out floor_out \
        --reference-cache floor_fem --fem-body level_set

``--volumes``: the particles' rest-volume rule (``fill.volumes`` of the contract: cell_share,
enclosed, wall; the contract's own when left out); ``--solid``: the closed surface's inside
filled (``contract.with_body``: a solid vase, where the contract has no fill). ``--reference-cache``: a folder where the
finite-element runs are kept and read back by a later call with the same inputs (the
reference at n_grid 48 costs minutes of one CPU core: compute it once, e.g. on this machine,
then spend a GPU call on the MPM levels). ``--check-kept``: say where the two finite-element
runs would be kept and whether they are, then stop (exit 2 where one is not): seconds, where the
study would spend minutes computing a reference that was not kept. The reference's settings not
named here are the profile's ``floor`` block's.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path


from knockgs_core.experiments import floor_note, floor_study, kept_reference_files
from knockgs_core.io import write_text

from _floor_object import add_object_arguments, floor_object



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_object_arguments(ap, default_object="pillow")
    ap.add_argument("--levels", type=int, nargs="+", required=True)
    ap.add_argument("--fem-n-grid", type=int, required=True)
    ap.add_argument("--fem-check-n-grid", type=int, required=True)
    ap.add_argument("--fit-steps", type=int, default=None)
    ap.add_argument("--record-factor", type=int, default=None,
                    help="the record simulated for the period, in Probe-A records (the floor block's when left out)")
    ap.add_argument("--body-resolution", type=int, default=None,
                    help="the fill grid a level-set body is measured on (the floor block's when left out)")
    ap.add_argument("--fem-body", default=None, choices=("voxel", "level_set"),
                    help="the reference's body (the profile's floor block's when left out)")
    ap.add_argument("--band-hz", type=float, default=None,
                    help="the record's slow band compared besides the whole record (the floor block's when left out)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reference-cache", type=Path, default=None)
    ap.add_argument("--check-kept", action="store_true", help="say whether the references are kept, then stop")
    args = ap.parse_args()
    if args.check_kept and args.reference_cache is None:
        ap.error("--check-kept needs --reference-cache")

    contract, settings = floor_object(args)
    changes = {"n_grid": tuple(args.levels), "fem_n_grid": args.fem_n_grid, "fem_check_n_grid": args.fem_check_n_grid}
    if args.fit_steps is not None:
        changes["fit_steps"] = args.fit_steps
    if args.record_factor is not None:
        changes["record_factor"] = args.record_factor
    if args.fem_body is not None:
        changes["fem_body"] = args.fem_body
    if args.body_resolution is not None:
        changes["fem_body_resolution"] = args.body_resolution
    if args.band_hz is not None:
        changes["band_hz"] = args.band_hz
    settings = dataclasses.replace(settings, **changes)
    if args.check_kept:
        kept = kept_reference_files(contract, settings, reference_cache=args.reference_cache)
        for name, (path, there) in kept.items():
            print(f"{name}: {path} {'kept' if there else 'NOT KEPT'}")
        raise SystemExit(0 if all(there for _, there in kept.values()) else 2)
    t0 = time.perf_counter()
    table = floor_study(contract, settings, device=args.device, log=lambda m: print(m, flush=True),
                        reference_cache=args.reference_cache)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = (f"floor_{args.object}_{contract.fill.volumes}{'_solid' if args.solid else ''}_{settings.fem_body}"
            + (f"_supports{args.snap_supports}" if args.snap_supports else ""))
    write_text(args.out / f"{stem}.csv", table.to_csv(index=False))  # atomic: a stopped run leaves the old file
    write_text(args.out / f"{stem}.md", floor_note(table, contract, settings))
    print(f"{stem}: {time.perf_counter() - t0:.0f} s on {args.device}")
    print(table.to_string())


if __name__ == "__main__":
    main()
