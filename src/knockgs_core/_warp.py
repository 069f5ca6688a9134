"""The one Warp initializer of the library, used by the simulator and the renderer.

Importing this module sets Warp's log level to warnings (no start-up banner in logs or CLI
output). :func:`init_warp` starts the Warp runtime once per process. On a CPU-only run it
prints nothing: Warp's native library reports a missing CUDA driver on the C-level stderr
(file descriptor 2), once per process (250 times in one workflow run), so while the runtime
starts, file descriptor 2 is pointed at the null device, then restored. When a CUDA device
is requested (the ``device`` argument or ``$KNOCKGS_DEVICE``), nothing is silenced.
:func:`warp_device` resolves a device name and raises a one-line
:class:`~knockgs_core.errors.InputError` naming the device when it is not available. The
name ``"cuda"`` (no index) is a GPU of the process's own: the first card no other process
holds, claimed for the process's life (:mod:`knockgs_core._device_claim`), so that the jobs of
a workflow run with ``--resources gpu=N`` on an N-GPU node each take a different card.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

import warp as wp

from ._device_claim import claim_slot
from .errors import InputError

__all__ = ["init_warp", "warp_device", "cuda_requested", "resolve_device"]

#: environment variable naming the default Warp device (see :func:`knockgs_core.sim.default_device`)
DEVICE_ENV = "KNOCKGS_DEVICE"

# keep Warp's start-up banner out of logs and CLI output (older and newer config names)
wp.config.quiet = True
if hasattr(wp, "LOG_WARNING"):
    wp.config.log_level = wp.LOG_WARNING

_READY = False
_CLAIMED: str | None = None  # "cuda:N", the card this process claimed for the name "cuda"


def cuda_requested(device: str | None = None) -> bool:
    """Whether ``device`` (or, when None, ``$KNOCKGS_DEVICE``) names a CUDA device."""
    name = device if device is not None else os.environ.get(DEVICE_ENV, "cpu")
    return str(name).strip().lower().startswith("cuda")


@contextlib.contextmanager
def _silenced_fd2() -> Iterator[None]:
    """Point the C-level stderr (file descriptor 2) at the null device for the block."""
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2 (a daemon): nothing to silence
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
        finally:
            os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def init_warp(device: str | None = None) -> None:
    """Start the Warp runtime once per process; silent on a CPU run (see the module docstring).

    ``device``: the Warp device the caller will use (``"cpu"``, ``"cuda:0"``; None: the
    ``$KNOCKGS_DEVICE`` default).
    """
    global _READY
    if _READY:
        return
    if cuda_requested(device):
        wp.init()
    else:
        with _silenced_fd2():
            wp.init()
    _READY = True


def _claimed_cuda() -> str:
    """The card this process holds for the name ``"cuda"``: claimed at the first call."""
    global _CLAIMED
    if _CLAIMED is None:
        count = wp.get_cuda_device_count()
        if count == 0:
            why = "no CUDA driver or GPU found" if not wp.is_cuda_available() else "no GPU"
            raise InputError("device", "device", f"Warp device 'cuda' is not available ({why})")
        devices = [wp.get_device(f"cuda:{i}") for i in range(count)]
        keys = [d.uuid or d.pci_bus_id or d.alias for d in devices]
        i = claim_slot(keys, log=lambda msg: print(f"knockgs: {msg}", file=sys.stderr, flush=True))
        _CLAIMED = f"cuda:{i}"
        wp.set_device(_CLAIMED)  # Warp's default device too: a launch or array naming none goes to the card
    return _CLAIMED


def resolve_device(device: str | None = None) -> str:
    """The device name ``device`` stands for, Warp started: ``"cuda"`` becomes the ``"cuda:N"``
    this process claimed (see the module docstring); other names are returned stripped; None is
    ``$KNOCKGS_DEVICE`` or ``"cpu"``."""
    name = str(device if device is not None else os.environ.get(DEVICE_ENV, "cpu")).strip()
    init_warp(name)
    if name.lower() == "cuda":
        return _claimed_cuda()
    return name


def warp_device(device: str | None = None):
    """The Warp device named ``device`` (None: ``$KNOCKGS_DEVICE`` or ``"cpu"``), Warp started;
    ``"cuda"`` is the card this process claimed (:func:`resolve_device`).

    Raises :class:`~knockgs_core.errors.InputError` (one line, naming the device) when the
    device does not exist or, for ``cuda:N``, when no CUDA driver or no such GPU is found.
    """
    name = resolve_device(device)
    try:
        return wp.get_device(name)
    except Exception as exc:  # Warp raises RuntimeError / ValueError by version
        why = "no CUDA driver or GPU found" if cuda_requested(name) and not wp.is_cuda_available() else str(exc)
        raise InputError("device", "device", f"Warp device {name!r} is not available ({why})") from None
