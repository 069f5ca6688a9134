"""knockgs asset: make, summarize and draw an object's Gaussian asset.

    knockgs asset make NAME --profile PROFILE -o OUT.ply [--normalized] [--particles P.npz]
        (with --normalized, the scene file OUT.scene.npz is written next to OUT.ply: with a
        rollout, the PLY and the scene file are what `knockgs render` needs)
    knockgs asset summary NAME --profile PROFILE [--json]
    knockgs asset figure NAME --profile PROFILE -o OUT.png
    knockgs asset init SPLAT -o CONTRACT.yaml [--up AXIS] [--opacity-threshold T]
        (a commented contract scaffold for a splat file, INRIA point_cloud.ply or SuperSplat
        .compressed.ply; every choice is a field to edit: docs/own_splat.md)

NAME is an object contract name (config/objects/NAME.yaml) or a path to a contract file.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

__all__ = ["register"]


def register(subparsers) -> None:
    p = subparsers.add_parser("asset", help="make, summarize or draw an object's Gaussian asset",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="asset_command", required=True)

    def common(sp):
        sp.add_argument("name", help="object contract name or path to a contract YAML")
        sp.add_argument("--profile", default="default", help="resolution profile (ci, default, paper)")
        sp.add_argument("--config-dir", default=None, help="configuration directory (default: see docs)")

    mk = sub.add_parser("make", help="write the asset as a standard 3DGS PLY")
    common(mk)
    mk.add_argument("-o", "--output", required=True, help="output .ply")
    mk.add_argument("--normalized", action="store_true",
                    help="write the preprocessed Gaussians in the normalized domain, the frame of rollouts, and "
                         "their scene file (OUT.scene.npz) for `knockgs render` "
                         "(default: the source/capture frame, as a reconstruction would be)")
    mk.add_argument("--particles", default=None, help="also write the simulated particles (.npz)")
    mk.set_defaults(func=_make)

    sm = sub.add_parser("summary", help="print GS / fill counts and filled cells")
    common(sm)
    sm.add_argument("--json", action="store_true", help="print JSON")
    sm.set_defaults(func=_summary)

    fg = sub.add_parser("figure", help="draw GS and fill particles (PNG)")
    common(fg)
    fg.add_argument("-o", "--output", required=True, help="output .png")
    fg.set_defaults(func=_figure)

    it = sub.add_parser("init", help="write a commented contract scaffold for a splat file")
    it.add_argument("splat", help="3DGS splat: INRIA point_cloud.ply or SuperSplat .compressed.ply")
    it.add_argument("-o", "--output", required=True, help="contract to write, NAME.yaml (NAME is the object's name)")
    it.add_argument("--up", default=None,
                    help="up axis in the splat's frame: x, -y, +z or a,b,c (default: the body's long axis, or the "
                         "short axis of a flat body; docs/own_splat.md)")
    it.add_argument("--opacity-threshold", type=float, default=0.05,
                    help="drop Gaussians of lower opacity (default 0.05)")
    it.set_defaults(func=_init)


def _load(args):
    from knockgs_core.contract import load_contract

    from ._common import check_command_inputs
    from .simulate import _contract_file

    check_command_inputs(args, {"NAME": _contract_file(args.name), "--config-dir": args.config_dir},
                         folders=("--config-dir",))
    return load_contract(args.name, args.profile, config_dir=args.config_dir)


def _make(args) -> int:
    from knockgs_core.io import check_outputs
    from knockgs_core.assets import build_asset, load_source_gaussians, save_particles, save_scene, scene_path, write_ply

    from ._common import contract_inputs

    contract = _load(args)
    check_outputs({"--output": args.output, "scene file": scene_path(args.output) if args.normalized else None,
                   "--particles": args.particles}, contract_inputs(contract))
    if args.normalized or args.particles:
        built = build_asset(contract)
    written = [args.output]
    if args.normalized:
        write_ply(built.gaussians, args.output)
        written.append(str(scene_path(args.output)))
        save_scene(built, written[-1])
    else:
        write_ply(load_source_gaussians(contract), args.output)
    if args.particles:
        save_particles(built.particles, args.particles, contract=contract)
        written.append(args.particles)
    print(f"wrote {', '.join(written)}")
    return 0


def _summary(args) -> int:
    from knockgs_core.assets import build_asset

    from knockgs_core.assets import source_selection

    contract = _load(args)
    built = build_asset(contract)
    s = built.summary()
    s = {"object": contract.name, "profile": contract.profile, "contract_hash": contract.hash,
         "n_grid": contract.sim.n_grid, "dt": contract.sim.dt,
         "fill_resolution": contract.fill.resolution if contract.fill.enabled else None, **s}
    if contract.asset.ply is not None:
        sel = source_selection(contract, built.normalization)
        s["source"] = {"layout": sel.layout, "counts": sel.counts, "repairs": sel.repairs._asdict()}
    if args.json:
        json.dump(s, sys.stdout, indent=2)
        print()
        return 0
    print(f"object {s['object']}  profile {s['profile']}  contract {s['contract_hash'][:12]}")
    print(f"  n_grid {s['n_grid']}  dt {s['dt']:g} s  fill resolution {s['fill_resolution']}")
    print(f"  Gaussians rendered {s['gaussians']}  (static support {s['static_gaussians']})")
    print(f"  GS particles {s['gs_particles']}  fill particles {s['fill_particles']}  "
          f"filled cells {s['fill_cells']}  total particles {s['particles']}")
    print("  regions " + "  ".join(f"{k} {v}" for k, v in s["regions"].items()))
    print("  probe particles " + "  ".join(f"{k} {v}" for k, v in s["probe_particles"].items()))
    if "source" in s:
        src = s["source"]
        c, r = src["counts"], src["repairs"]
        print(f"  source {src['layout']}: file {c['file']}  profile sample {c['profile']}  below opacity "
              f"{c['below_opacity']}  outside crop {c['outside_crop']}  kept {c['kept']}")
        print(f"  reading rules: opacity saturated {r['opacity_saturated']}  zero quaternions "
              f"{r['zero_quaternions']}  scales clamped {r['scales_clamped']}")
    return 0


def _figure(args) -> int:
    from knockgs_core.assets import build_asset
    from knockgs_core.io import check_outputs
    from knockgs_core.assets._figure import asset_figure

    from ._common import contract_inputs

    contract = _load(args)
    check_outputs({"--output": args.output}, contract_inputs(contract))
    built = build_asset(contract)
    removed = None
    if contract.asset.ply is not None:
        from knockgs_core.assets import source_selection

        removed = source_selection(contract, built.normalization).removed_means
    supports = [bc.box for bc in contract.sim.boundaries if getattr(bc, "box", None) is not None
                and type(bc).__name__ == "FixedCuboid"]
    probes = [(k, p.force, p.box) for k, p in contract.probes.items()]
    asset_figure(built, args.output, title=f"{contract.name} ({contract.profile})", removed_means=removed,
                 supports=supports, probes=probes, camera_image=_camera_view(contract, built))
    print(f"wrote {args.output}")
    return 0


def _camera_view(contract, built):
    """The asset at rest through the contract camera, [H, W, 3] in [0, 1] (CPU)."""
    from knockgs_core.render import camera_from_contract
    from knockgs_core.render import render

    g = built.gaussians
    cam = camera_from_contract(contract.camera)
    return np.asarray(render(g.means, g.covariances(), g.colors(), g.opacities, cam).rgb)


def _init(args) -> int:
    from knockgs_core.assets import contract_text, scaffold_contract
    from knockgs_core.contract import load_contract
    from knockgs_core.io import check_outputs, atomic_write

    from ._common import check_command_inputs

    check_command_inputs(args, {"SPLAT": args.splat})
    check_outputs({"--output": args.output}, {"SPLAT": args.splat})
    s = scaffold_contract(args.splat, args.output, up=args.up, opacity_threshold=args.opacity_threshold)
    with atomic_write(args.output, mode="w") as fh:
        fh.write(contract_text(s))
    load_contract(args.output, "ci")  # the loader accepts what was written
    c = s.counts
    print(f"wrote {args.output}: {c['kept']} of {c['file']} Gaussians kept ({c['below_opacity']} below opacity "
          f"{args.opacity_threshold}, {c['floaters_removed']} floaters outside the crop); up {s.up_rule}")
    return 0
