"""Helpers shared by the subcommands (private): argument types and the inputs of a contract."""

from __future__ import annotations

import argparse
import math

__all__ = ["check_command_inputs", "contract_inputs", "image_side", "nonnegative_float", "nonnegative_int",
           "positive_float", "positive_int"]


def contract_inputs(contract) -> dict:
    """The files a loaded contract reads (outputs may not be any of them)."""
    return {"--object": contract.source, "asset.ply": contract.asset.ply,
            "candidates": contract.candidates_path, "targets": contract.targets_path}


def check_command_inputs(args, inputs: dict, *, folders: tuple[str, ...] = ()) -> None:
    """Check a command's input paths before any work (:func:`knockgs_core.io.check_inputs`:
    each exists, is a regular file or the folder its option expects, is readable and within
    the size bound of its kind) and record them on ``args``, for the one line that names what
    was being processed should a programming error stop the command (:func:`knockgs_core.cli.main`)."""
    from ..io import check_inputs

    args.inputs_ = {k: v for k, v in inputs.items() if v is not None and v != []}
    check_inputs(inputs, folders=folders)


def _number(kind, text: str, ok, rule: str, limit: float | None = None):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'} {rule}, got '{text}'") from None
    if not (math.isfinite(value) and ok(value)) or (limit is not None and value > limit):
        bound = f" and at most {limit:g}" if limit is not None else ""
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'} {rule}{bound}, got '{text}'")
    return value


def positive_int(text: str) -> int:
    return _number(int, text, lambda v: v > 0, "> 0")


def nonnegative_int(text: str) -> int:
    return _number(int, text, lambda v: v >= 0, ">= 0")


def nonnegative_float(text: str) -> float:
    return _number(float, text, lambda v: v >= 0, ">= 0")


def positive_float(text: str) -> float:
    return _number(float, text, lambda v: v > 0, "> 0")


def image_side(text: str) -> int:
    """An image width or height in pixels: 1 .. 8192."""
    return _number(int, text, lambda v: v > 0, "> 0", limit=8192)
