"""The ``knockgs`` command line.

Each subcommand lives in its own module ``knockgs_core.cli.<name>`` that defines
``register(subparsers)`` (cheap: no heavy imports at module level) and sets
``func`` on its parser.

Errors reach the user as one line on stderr, ``knockgs COMMAND: error: FILE: field 'F':
WHAT``, never as a traceback: :class:`knockgs_core.errors.KnockGSError` (bad input, a
stopped simulation) and, mapped here at the boundary, the errors of reading and writing
files (``OSError`` with its file name, including a full disk or a missing permission;
``ValueError``, ``UnicodeDecodeError``, ``EOFError``, ``zipfile.BadZipFile``, pyarrow's
``ArrowInvalid``; ``MemoryError``) give exit code 2; Ctrl-C (``KeyboardInterrupt``)
prints ``interrupted`` and gives exit code 130. Any other exception (a ``TypeError`` or
``RuntimeError`` from NumPy or Warp: a programming error, or an input no reader foresaw) is
one line too, never hidden: ``internal error``, the exception, the command's input files
and the hint to rerun with ``KNOCKGS_TRACEBACK=1``, which shows the traceback of any error;
exit code 1. Commands check their input and output paths before any work
(:func:`knockgs_core.io.check_inputs`, :func:`knockgs_core.io.check_outputs`).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys
import zipfile

from ..errors import InputWarning, KnockGSError

__all__ = ["TRACEBACK_ENV", "main", "build_parser", "describe_error", "describe_internal_error"]

#: subcommand modules, in the order they appear in ``knockgs --help``
_COMMANDS = ("simulate", "asset", "calibrate", "render", "observe", "discrepancy")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (exit code 2), like every other refusal."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = _Parser(prog="knockgs", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"knockgs {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


#: errors mapped to one line (exit code 2) at the boundary, besides KnockGSError
_MAPPED = (OSError, ValueError, EOFError, zipfile.BadZipFile, MemoryError)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


#: the environment variable that shows the traceback of an error instead of its one line
TRACEBACK_ENV = "KNOCKGS_TRACEBACK"


def _inputs_of(args) -> str:
    """The command's input files, as recorded by its input check (``--opt=path, ...``)."""
    inputs = getattr(args, "inputs_", None) or {}
    items = []
    for field, value in inputs.items():
        for v in (value if isinstance(value, (list, tuple)) else [value]):
            items.append(f"{field}={os.fspath(v)}")
    if len(items) > 4:
        items = items[:4] + [f"... ({len(items) - 4} more)"]
    return ", ".join(items)


def describe_error(exc: BaseException, args=None) -> str:
    """One line for a mapped error: the file (when known) and the cause; where the error names
    no file (a ``ValueError`` from deep inside NumPy), the command's inputs (``args``)."""
    if isinstance(exc, KnockGSError):
        return _one_line(exc)
    if isinstance(exc, OSError):
        names = [n for n in (exc.filename, exc.filename2) if n is not None]
        why = exc.strerror or str(exc) or type(exc).__name__
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            why += " (nothing was replaced: the previous file, if any, is unchanged)"
        where = ": ".join(os.fsdecode(n) for n in names)
        return _one_line(f"{where}: {why}" if where else f"{type(exc).__name__}: {why}")
    where = _inputs_of(args) if args is not None else ""
    if isinstance(exc, MemoryError):
        return _one_line(f"out of memory ({exc or 'an array too large for this machine'})"
                         + (f" while processing {where}" if where else "")
                         + "; check the sizes the inputs and options ask for")
    return _one_line(f"{type(exc).__name__}: {exc}" + (f" (while processing {where})" if where else ""))


def describe_internal_error(exc: BaseException, args) -> str:
    """One line for an unforeseen exception: never hidden, never a traceback unless asked for."""
    where = _inputs_of(args)
    return _one_line(f"internal error ({type(exc).__name__}: {exc})"
                     + (f" while processing {where}" if where else "")
                     + f"; rerun with {TRACEBACK_ENV}=1 for the traceback, and please report it")


def _show_warning(message, category, filename, lineno, file=None, line=None):
    if issubclass(category, InputWarning):
        print(f"knockgs: warning: {_one_line(message)}", file=file or sys.stderr)
    else:
        _show_warning.default(message, category, filename, lineno, file, line)


def main(argv: list[str] | None = None) -> int:
    import warnings

    parser = build_parser()
    args = parser.parse_args(argv)
    if warnings.showwarning is not _show_warning:
        _show_warning.default = warnings.showwarning
        warnings.showwarning = _show_warning
    try:
        return int(args.func(args) or 0)
    except KnockGSError as exc:
        print(f"knockgs {args.command}: error: {describe_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"knockgs {args.command}: interrupted", file=sys.stderr)
        return 130
    except _MAPPED as exc:
        if os.environ.get(TRACEBACK_ENV):
            raise
        print(f"knockgs {args.command}: error: {describe_error(exc, args)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a programming error, or input no reader foresaw: one line, exit 1
        if os.environ.get(TRACEBACK_ENV):
            raise
        print(f"knockgs {args.command}: {describe_internal_error(exc, args)}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
