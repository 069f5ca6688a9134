"""Estimate (s_E, s_rho) for query descriptors from a candidate library.

Reads a library CSV (``case_name, E_scale, density_scale`` + the five descriptor columns)
and a query CSV (``case_name`` + the five columns; other columns, labels included, are
ignored) and writes the frozen estimates as JSON. Heavy imports happen inside :func:`run`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..errors import InputError

__all__ = ["register", "run"]


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``calibrate`` subcommand to the dispatcher's subparsers.

    The ``--method`` choices are the deployable methods of the calibration registry and
    their aliases (the parameter-nearest oracle needs target labels: not a CLI method).
    """
    from ..calibration import DEPLOYABLE_METHODS, METHOD_ALIASES

    aliases = [a for a, name in METHOD_ALIASES.items() if name in DEPLOYABLE_METHODS]
    method_help = (f"one of: {', '.join(DEPLOYABLE_METHODS)} (aliases: "
                   + ", ".join(f"{a} = {METHOD_ALIASES[a]}" for a in aliases) + ")")
    parser = subparsers.add_parser(
        "calibrate",
        help="estimate (s_E, s_rho) from Probe-A descriptors and a candidate library",
        description=__doc__.splitlines()[0],
    )
    parser.add_argument("--library", required=True, metavar="L.csv",
                        help="candidate library: case_name, E_scale, density_scale + descriptors")
    parser.add_argument("--queries", required=True, metavar="Q.csv",
                        help="query descriptors: case_name + descriptors (labels ignored)")
    parser.add_argument("--method", required=True, choices=(*DEPLOYABLE_METHODS, *aliases),
                        metavar="METHOD", help=method_help)
    parser.add_argument("--k", default=None,
                        help="neighbour count for response_knn / local_ridge (response_knn also accepts 'cv')")
    parser.add_argument("--alpha", default=None,
                        help="ridge strength for global_ridge / local_ridge, or 'cv'")
    parser.add_argument("--output", required=True, metavar="OUT.json", help="estimates (JSON)")
    parser.set_defaults(func=run)
    return parser


def _parse_k(text: str):
    if text == "cv":
        return "cv"
    try:
        return int(text)
    except ValueError:
        message = f"expected an integer or 'cv', got {text!r}"
        raise InputError("command line", "--k", message) from None


def _parse_alpha(text: str):
    if text == "cv":
        return "cv"
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        message = f"expected a finite number >= 0 or 'cv', got {text!r}"
        raise InputError("command line", "--alpha", message) from None
    return value


def run(args: argparse.Namespace) -> int:
    """Run ``knockgs calibrate``; bad input raises :class:`~knockgs_core.errors.InputError`."""
    from ..io import check_outputs, write_json
    from ..calibration import calibrate
    from ._common import check_command_inputs

    check_command_inputs(args, {"--library": args.library, "--queries": args.queries})
    output = Path(args.output)
    check_outputs({"--output": output}, {"--library": args.library, "--queries": args.queries})
    params = {}
    if args.k is not None:
        params["k"] = _parse_k(args.k)
    if args.alpha is not None:
        params["alpha"] = _parse_alpha(args.alpha)
    result = calibrate(args.library, args.queries, args.method, **params)

    write_json(output, result)
    return 0
