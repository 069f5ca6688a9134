"""Estimate (s_E, s_rho) for query descriptors from a candidate library.

Reads a library CSV (``case_name, E_scale, density_scale`` + the five descriptor columns)
and a query CSV (``case_name`` + the five columns; other columns, labels included, are
ignored) and writes the frozen estimates as JSON. Heavy imports happen inside :func:`run`.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..errors import InputError

__all__ = ["register", "run"]

#: deployable methods (the parameter-nearest oracle needs target labels: not a CLI method)
_METHOD_HELP = "default, nearest, knn, global_ridge, local_ridge"


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``calibrate`` subcommand to the dispatcher's subparsers."""
    parser = subparsers.add_parser(
        "calibrate",
        help="estimate (s_E, s_rho) from Probe-A descriptors and a candidate library",
        description=__doc__.splitlines()[0],
    )
    parser.add_argument("--library", required=True, metavar="L.csv",
                        help="candidate library: case_name, E_scale, density_scale + descriptors")
    parser.add_argument("--queries", required=True, metavar="Q.csv",
                        help="query descriptors: case_name + descriptors (labels ignored)")
    parser.add_argument("--method", required=True, help=f"one of: {_METHOD_HELP}")
    parser.add_argument("--k", default=None,
                        help="neighbour count for knn / local_ridge (knn also accepts 'cv')")
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
        return float(text)
    except ValueError:
        message = f"expected a number or 'cv', got {text!r}"
        raise InputError("command line", "--alpha", message) from None


def run(args: argparse.Namespace) -> int:
    """Run ``knockgs calibrate``; bad input raises :class:`~knockgs_core.errors.InputError`."""
    import json

    from ..calibration import calibrate

    output = Path(args.output)
    for flag, path in (("--library", args.library), ("--queries", args.queries)):
        if output.resolve() == Path(path).resolve():
            raise InputError(str(output), "--output", f"would overwrite the {flag} input")
    params = {}
    if args.k is not None:
        params["k"] = _parse_k(args.k)
    if args.alpha is not None:
        params["alpha"] = _parse_alpha(args.alpha)
    result = calibrate(args.library, args.queries, args.method, **params)

    text = json.dumps(result, indent=2, allow_nan=False) + "\n"
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(f".{output.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, output)
    return 0
