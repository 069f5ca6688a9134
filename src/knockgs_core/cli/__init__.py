"""The ``knockgs`` command line.

Each subcommand lives in its own module ``knockgs_core.cli.<name>`` that defines
``register(subparsers)`` (cheap: no heavy imports at module level) and sets
``func`` on its parser. Errors derived from :class:`knockgs_core.errors.KnockGSError`
are printed as one line and give exit code 2; nothing prints a traceback for bad input.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import KnockGSError

__all__ = ["main", "build_parser"]

#: subcommand modules, in the order they appear in ``knockgs --help``
_COMMANDS = ("simulate", "asset", "calibrate", "render", "discrepancy")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(prog="knockgs", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"knockgs {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KnockGSError as exc:
        print(f"knockgs {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
