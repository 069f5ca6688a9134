"""``knockgs discrepancy``: find the effect a calibrated model lacks, add it, report before/after.

Subcommands: ``run`` (the loop on a measured file, writes a report), ``make-case`` (a
synthetic measured case with a planted effect; the truth goes to a separate folder),
``evaluate`` (score a run against a case's truth) and ``table`` (collect evaluated cases).
Heavy imports happen inside the handlers.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from ..errors import InputError
from ._common import contract_inputs, nonnegative_float, nonnegative_int, positive_int

__all__ = ["register"]


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'SE,SRHO' (two numbers), got '{text}'") from None
    if not all(math.isfinite(v) and v > 0 for v in (a, b)):
        raise argparse.ArgumentTypeError(f"expected two finite scales > 0, got '{text}'")
    return a, b


def _level(text: str):
    """``low``, ``high`` or a finite fraction > 0."""
    if text in ("low", "high"):
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected 'low', 'high' or a finite fraction > 0, got '{text}'")
    return value


def _fraction(text: str) -> float:
    """A finite fraction in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value <= 1):
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1], got '{text}'")
    return value


def _common(p) -> None:
    p.add_argument("--object", required=True, help="object name (config/objects/NAME.yaml) or a contract path")
    p.add_argument("--profile", default="default", help="resolution profile: ci, default or paper")
    p.add_argument("--particles", help="particles .npz from `knockgs asset` (default: build the asset)")
    p.add_argument("--device",
                   help="Warp device (cpu; cuda: a GPU no other process holds; cuda:0); default $KNOCKGS_DEVICE or cpu")
    p.add_argument("--config-dir", help="folder holding objects/ (default: the project's config/)")


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``discrepancy`` and its subcommands to the dispatcher's subparsers."""
    parser = subparsers.add_parser("discrepancy", help="find, add and report a missing physical effect",
                                   description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="discrepancy_command", required=True)

    p = sub.add_parser("run", help="run the discrepancy loop on measured trajectories and write a report")
    _common(p)
    p.add_argument("--measured", required=True, metavar="FILE", help="calibration-probe trajectories (.parquet, .csv, .npz)")
    p.add_argument("--probe", help="probe of the measurement (default: its metadata, then the contract's calibration probe)")
    p.add_argument("--heldout-probe", action="append", default=[], metavar="NAME",
                   help="held-out probe to predict (repeatable; never used in the loop)")
    p.add_argument("--heldout-measured", action="append", default=[], metavar="PROBE=FILE",
                   help="measurement of a held-out probe, only to score the predictions (repeatable)")
    p.add_argument("--library-rollout", action="append", default=[], metavar="FILE",
                   help="candidate-library rollout (.parquet, theta in its metadata; repeatable): base calibration by "
                        "local ridge instead of Gauss-Newton from (1, 1)")
    p.add_argument("--catalogue", help="comma-separated catalogue keys to consider (default: all that apply)")
    p.add_argument("--max-effects", type=nonnegative_int, default=2, help="most effects to add (default 2)")
    p.add_argument("--n-grid", type=positive_int, metavar="N",
                   help="simulate the loop's model on a grid of N cells per axis, fill refined with it (default: the "
                        "profile's grid, or the floor table's choice; a GPU --device for fine grids)")
    p.add_argument("--floor-table", metavar="FILE",
                   help="the object's floor table (floor_{object}.csv): without --n-grid, run at its coarsest level whose "
                        "distance to the finite-element reference is at most half of --smallest-effect, else at its finest; "
                        "with it, at that level; say which, and widen theta's interval by that level's calibration bias")
    p.add_argument("--smallest-effect", type=_fraction, default=0.2, metavar="F",
                   help="with --floor-table: the smallest effect to name, as a fraction of the response (default 0.2)")
    p.add_argument("-o", "--output", required=True, metavar="DIR",
                   help="report folder (report.md, result.json, predictions.npz, figures)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_run)

    p = sub.add_parser("make-case", help="write a synthetic measured case with a planted effect (truth kept apart)")
    _common(p)
    p.add_argument("--case", required=True, help="case name; a standard case (see docs/discrepancy.md) unless --planted is given")
    p.add_argument("--planted", help="planted effect: none, damping, gravity, plasticity, poisson, stiffness_gradient_z, "
                                     "support_slip, force_pulse, hidden_mass")
    p.add_argument("--level", type=_level, default="low", help="low (12%% held-out change), high (25%%) or a fraction")
    p.add_argument("--theta", type=_pair, default=(0.8, 1.2), help="true 'SE,SRHO' (default 0.8,1.2)")
    p.add_argument("--noise", type=nonnegative_float, default=0.02,
                   help="noise std as a fraction of the RMS displacement, >= 0 (default 0.02)")
    p.add_argument("--observation", default="gs_identity", help="gs_identity, gs_tracks (no identity) or all_identity")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--measured-dir", required=True, metavar="DIR", help="where the measured files go")
    p.add_argument("--truth-dir", required=True, metavar="DIR", help="where the truth goes (only `evaluate` reads it)")
    p.set_defaults(func=_make_case)

    p = sub.add_parser("evaluate", help="score a run against its case's truth (one table row as JSON)")
    p.add_argument("--run-dir", required=True, metavar="DIR", help="output folder of `discrepancy run`")
    p.add_argument("--truth-dir", required=True, metavar="DIR")
    p.add_argument("-o", "--output", required=True, metavar="ROW.json")
    p.add_argument("--markdown", metavar="EVAL.md", help="also write a short evaluation page")
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("table", help="collect evaluated rows into CSV and Markdown tables")
    p.add_argument("rows", nargs="+", metavar="ROW.json")
    p.add_argument("--csv", required=True)
    p.add_argument("--md", required=True)
    p.add_argument("--figure", help="also write a bar chart of the RMSE before/after (.png)")
    p.set_defaults(func=_table)
    return parser


def _common_inputs(args, **inputs) -> None:
    """The command's input paths, checked before any work (the contract file when --object is
    a path, --particles, --config-dir, and ``inputs``)."""
    from ._common import check_command_inputs
    from .simulate import _contract_file

    folders = tuple(k for k in inputs if k.endswith("-dir")) + ("--config-dir",)
    check_command_inputs(args, {"--object": _contract_file(args.object) if hasattr(args, "object") else None,
                                "--particles": getattr(args, "particles", None),
                                "--config-dir": getattr(args, "config_dir", None), **inputs}, folders=folders)


def _load(args, contract):
    if args.particles:
        from ..assets import load_particles

        return load_particles(args.particles, contract=contract)
    from ..assets import build_asset

    return build_asset(contract).particles


def _run(args) -> int:
    from ..discrepancy import LoopSettings, run_files

    held = {}
    for item in args.heldout_measured:
        if "=" not in item:
            raise InputError("command line", "--heldout-measured", f"expected PROBE=FILE, got '{item}'")
        name, path = item.split("=", 1)
        if name in held:
            raise InputError("command line", "--heldout-measured", f"probe '{name}' is given twice")
        held[name] = path
    _common_inputs(args, **{"--measured": args.measured, "--heldout-measured": list(held.values()),
                            "--library-rollout": list(args.library_rollout), "--floor-table": args.floor_table})
    settings = LoopSettings(max_effects=args.max_effects, catalogue=tuple(args.catalogue.split(",")) if args.catalogue else None)
    say = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    result = run_files(args.object, args.profile, args.measured, args.output, particles=args.particles, probe=args.probe,
                       heldout_probes=args.heldout_probe, heldout_measured=held, library_rollouts=args.library_rollout,
                       settings=settings, device=args.device, config_dir=args.config_dir, progress=say,
                       n_grid=args.n_grid, floor_table=args.floor_table, smallest_effect=args.smallest_effect)
    if result.resolution:
        print(f"resolution: {result.resolution['statement']}", file=sys.stderr)
    print(f"{result.verdict} -> {args.output}/report.md", file=sys.stderr)
    return 0


def _make_case(args) -> int:
    from ..io import check_outputs
    from ..contract import load_contract
    from ..discrepancy import CaseSpec, default_cases, make_case

    _common_inputs(args)
    contract = load_contract(args.object, args.profile, config_dir=args.config_dir)
    check_outputs({"--measured-dir": args.measured_dir, "--truth-dir": args.truth_dir},
                  {**contract_inputs(contract), "--particles": args.particles},
                  directories={"--measured-dir": ("measured_*.parquet",), "--truth-dir": ("truth.json", "clean.npz")})
    particles = _load(args, contract)
    if args.planted is None:
        std = {c.name: c for c in default_cases(targets_path=contract.targets_path)}
        if args.case not in std:
            raise InputError("command line", "--case", f"'{args.case}' is not a standard case ({', '.join(std)}); give --planted")
        spec = std[args.case]
    else:
        spec = CaseSpec(name=args.case, planted=args.planted, level=args.level, theta=args.theta, noise_rel=args.noise,
                        observation=args.observation, seed=args.seed)
    truth = make_case(spec, contract, particles, measured_dir=args.measured_dir, truth_dir=args.truth_dir, device=args.device)
    print(f"case {spec.name}: planted {truth['planted_effect']} -> {args.measured_dir} (truth in {args.truth_dir})",
          file=sys.stderr)
    return 0


def _evaluate(args) -> int:
    from ..discrepancy import evaluate_files

    _common_inputs(args, **{"--run-dir": args.run_dir, "--truth-dir": args.truth_dir})
    evaluate_files(args.run_dir, args.truth_dir, args.output, markdown=args.markdown)
    return 0


def _table(args) -> int:
    from ..discrepancy import case_table, table_figure, write_case_table

    from ..io import check_outputs

    from ._common import check_command_inputs

    check_command_inputs(args, {"ROW.json": list(args.rows)})
    check_outputs({"--csv": args.csv, "--md": args.md, "--figure": args.figure}, {"ROW.json": list(args.rows)})
    rows = []
    for p in args.rows:
        try:
            with open(p, encoding="utf-8") as fh:
                rows.append(json.load(fh))
        except (OSError, ValueError) as exc:
            raise InputError(p, "ROW.json", f"not a readable JSON row ({getattr(exc, 'strerror', None) or exc})") from None
        if not isinstance(rows[-1], dict):
            raise InputError(p, "ROW.json", "must be a JSON object (a row of `knockgs discrepancy evaluate`)")
    try:
        df = case_table(rows)
    except KeyError as exc:
        raise InputError("ROW.json", str(exc).strip("'"),
                         "missing from a row (not written by `knockgs discrepancy evaluate`?)") from None
    write_case_table(df, args.csv, args.md)
    if args.figure:
        table_figure(df, args.figure)
    print(f"{int(df['accepted'].sum())}/{len(df)} cases accepted -> {args.csv}", file=sys.stderr)
    return 0
