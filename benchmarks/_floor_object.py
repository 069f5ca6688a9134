"""The floor benchmarks' object: the command-line options that name it and its body, and the
contract they give (helpers of floor_levels.py, floor_amplitude.py, reference_convergence.py and
reference_bodies.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def add_object_arguments(ap, *, default_object: str) -> None:
    """``--object``, ``--profile``, ``--volumes``, ``--solid``, ``--one-body`` and ``--snap-supports``
    on ``ap``."""
    ap.add_argument("--object", default=default_object)
    ap.add_argument("--profile", default="config", help="config file stem: ci, config (default), paper")
    ap.add_argument("--volumes", default=None, choices=("cell_share", "enclosed", "wall"))
    ap.add_argument("--solid", action="store_true", help="fill the closed surface's inside (contract.with_body)")
    ap.add_argument("--one-body", type=int, default=None, metavar="N",
                    help="measure every level's body on one fill grid of N cells (fill.body_resolution; "
                         "the reference's --body-resolution gives both models one body)")
    ap.add_argument("--snap-supports", type=int, default=None, metavar="N",
                    help="move each still support box's faces to the nearest multiple of grid_lim / N "
                         "(onto grid planes of every level whose n_grid N divides)")


def add_reference_arguments(ap) -> None:
    """``--levels`` (the MPM's), ``--fem-n-grid``, ``--fem-check-n-grid`` and ``--body-resolution``
    (the reference's) on ``ap``."""
    ap.add_argument("--levels", type=int, nargs="+", required=True)
    ap.add_argument("--fem-n-grid", type=int, required=True)
    ap.add_argument("--fem-check-n-grid", type=int, required=True)
    ap.add_argument("--body-resolution", type=int, default=None,
                    help="the fill grid a level-set body is measured on (the floor block's when left out)")


def reference_settings(args, settings, **changes):
    """``settings`` with ``args``' levels and reference grids (:func:`add_reference_arguments`), its
    body resolution where given, and ``changes``."""
    changes = {"n_grid": tuple(args.levels), "fem_n_grid": args.fem_n_grid, "fem_check_n_grid": args.fem_check_n_grid,
               **({"fem_body_resolution": args.body_resolution} if args.body_resolution is not None else {}), **changes}
    return dataclasses.replace(settings, **changes)


def floor_object(args):
    """(the contract ``args`` name, with its body and supports, the profile's floor settings)."""
    from knockgs_core.contract import load_contract, with_body
    from knockgs_core.experiments import FloorSettings

    profile = {"config": "default"}.get(args.profile, args.profile)
    block = yaml.safe_load((ROOT / "config" / f"{args.profile}.yaml").read_text())["floor"]
    settings = FloorSettings.from_config({k: v for k, v in block.items() if k not in ("enabled", "objects")})
    contract = with_body(load_contract(args.object, profile), volumes=args.volumes, solid=args.solid)
    if args.snap_supports:
        contract = snapped_supports(contract, args.snap_supports)
    if getattr(args, "one_body", None):
        contract = dataclasses.replace(contract, fill=dataclasses.replace(contract.fill, body_resolution=int(args.one_body)))
    return contract, settings


def snapped_supports(contract, n: int):
    """``contract`` with each support box's faces moved to the nearest multiple of
    ``grid_lim / n``: on a grid plane at every n_grid that ``n`` divides, where the MPM holds the
    nodes on the face and the finite-element mesh has its face there."""
    from knockgs_core.sim._config import Box, FixedCuboid

    step = contract.sim.grid_lim / n
    boundaries = []
    for bc in contract.sim.boundaries:
        if isinstance(bc, FixedCuboid):
            lo = [round((c - h) / step) * step for c, h in zip(bc.box.center, bc.box.half_size)]
            hi = [round((c + h) / step) * step for c, h in zip(bc.box.center, bc.box.half_size)]
            box = Box(tuple((a + b) / 2 for a, b in zip(lo, hi)), tuple((b - a) / 2 for a, b in zip(lo, hi)))
            bc = dataclasses.replace(bc, box=box)
        boundaries.append(bc)
    return dataclasses.replace(contract, sim=dataclasses.replace(contract.sim, boundaries=tuple(boundaries)))
