"""Errors that reach a user: each names the file (or object) and the field at fault."""

from __future__ import annotations

__all__ = ["KnockGSError", "InputError", "InputWarning", "SimulationError"]


class KnockGSError(Exception):
    """Base class for errors that the CLI reports as a one-line message (exit code 2)."""


class InputError(KnockGSError, ValueError):
    """Bad input: names the source (file path or object) and the field.

    Parameters
    ----------
    source:
        The file path (or a short description of the in-memory object) that holds the bad value.
    field:
        The field, column or key at fault.
    message:
        What is wrong with it.
    """

    def __init__(self, source: object, field: str, message: str):
        self.source = str(source)
        self.field = field
        self.message = message
        super().__init__(f"{self.source}: field '{field}': {message}")


class SimulationError(KnockGSError, RuntimeError):
    """A simulation stopped by a guard (non-finite state, CFL violation)."""


class InputWarning(UserWarning):
    """Input that is used but probably not what was meant (the CLI prints it as one line)."""
