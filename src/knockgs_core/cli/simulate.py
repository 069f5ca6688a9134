"""``knockgs simulate``: one rollout of an object contract, written as Parquet."""

from __future__ import annotations

import argparse
import math
import sys

from ..errors import InputError

__all__ = ["THETA_RANGE", "register", "run"]

#: the material scales a command accepts: factors on the contract's E and rho (the candidates
#: span 0.5 .. 1.75); outside it a scaled material is not a plausible version of the object, and
#: a scale such as 1e-320 would reach the solver as a zero density
THETA_RANGE = (1e-3, 1e3)


def _contract_file(name_or_path):
    """The contract file an --object value names when it is a path (a name is looked up)."""
    s = str(name_or_path)
    return s if s.endswith((".yaml", ".yml")) or "/" in s else None


def _theta(text: str) -> tuple[float, float]:
    try:
        s_e, s_rho = (float(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'SE,SRHO' (two numbers), got '{text}'") from None
    return s_e, s_rho


def register(sub) -> None:
    p = sub.add_parser("simulate", help="run one MPM rollout of an object under a probe", description=__doc__)
    p.add_argument("--object", required=True, help="object name (config/objects/NAME.yaml) or a contract path")
    p.add_argument("--profile", default="default", help="resolution profile: ci, default or paper")
    p.add_argument("--theta", type=_theta, default=(1.0, 1.0), help="material scales 'SE,SRHO' (default 1,1)")
    p.add_argument("--probe", required=True, help="probe name from the contract, e.g. standard_x")
    p.add_argument("-o", "--output", required=True, help="output rollout .parquet")
    p.add_argument("--particles", help="particles .npz from `knockgs asset` (default: build the asset)")
    p.add_argument("--export-F", dest="export_F", metavar="R.F.parquet",
                   help="also write the GS particles' deformation gradients here (needed by `knockgs render`)")
    p.add_argument("--device",
                   help="Warp device (cpu; cuda: a GPU no other process holds; cuda:0); default $KNOCKGS_DEVICE or cpu")
    p.add_argument("--deterministic", action="store_true",
                   help="sum P2G in int64 fixed point, so that a GPU gives the same rollout bit for bit on every run "
                        "(1.01-1.13x a substep there; the paper profile's setting). CPU rollouts are reproducible "
                        "without it, and it makes them ~1.4x slower and changes their last bits")
    p.add_argument("--config-dir", help="folder holding objects/ (default: the project's config/)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..io import check_outputs
    from ..contract import load_contract
    from ..rollout import RolloutStream, run_rollout
    from ._common import check_command_inputs, contract_inputs

    check_command_inputs(args, {"--object": _contract_file(args.object), "--particles": args.particles,
                                "--config-dir": args.config_dir}, folders=("--config-dir",))
    lo, hi = THETA_RANGE
    if not all(math.isfinite(v) and lo <= v <= hi for v in args.theta):
        raise InputError("command line", "--theta", f"scales must be finite numbers in [{lo:g}, {hi:g}] (factors on "
                         f"the contract's E and rho), got {args.theta}")
    contract = load_contract(args.object, args.profile, config_dir=args.config_dir)
    check_outputs({"--output": args.output, "--export-F": args.export_F},
                  {**contract_inputs(contract), "--particles": args.particles})
    if args.probe not in contract.probes:
        raise InputError(contract.source, "probes", f"unknown probe '{args.probe}'; known: {', '.join(contract.probes)}")
    particles = None
    if args.particles:
        from ..assets import load_particles

        particles = load_particles(args.particles, contract=contract)

    def progress(frame: int, n_frames: int, stats: dict) -> None:
        if not args.quiet:
            print(f"frame {frame}/{n_frames - 1}  cfl {stats['cfl']:.3g}  min det F {stats['min_det_F']:.5f}",
                  file=sys.stderr, flush=True)

    # the files are written frame by frame while the rollout runs (atomically: none on a failure)
    stream = RolloutStream(args.output, args.export_F)
    rollout = run_rollout(contract, args.theta, args.probe, particles=particles, device=args.device,
                          deterministic=bool(args.deterministic), export_F=bool(args.export_F), progress=progress,
                          stream=stream)
    try:
        stream.wait()
    except BaseException:  # an interrupt while the last frames are written: no file either
        stream.abort()
        raise
    m = rollout.meta
    print(
        f"{m['object']}/{m['profile']} theta=({m['theta'][0]:g}, {m['theta'][1]:g}) probe={args.probe}: "
        f"{m['n_gs']} GS + {m['n_fill']} fill particles, {m['stats']['steps']} substeps in {m['wall_seconds']:.2f} s "
        f"-> {args.output}",
        file=sys.stderr,
    )
    return 0
