"""One GPU per process on a machine with several: the claim behind the device name ``"cuda"``.

A workflow run on a node with N GPUs (``snakemake --resources gpu=N``) starts up to N GPU jobs
at once, and Snakemake does not say which card each may use. With the device ``"cuda"`` (no
index) each process claims a card of its own: the first one no other process holds, held
until the process exits (an exclusive ``flock`` on a file named for the card's UUID, so a
card masked by ``CUDA_VISIBLE_DEVICES`` under another ordinal, as Slurm does, is still the
same card). The operating system releases the lock when the process ends, however it ends:
a killed job frees its card. When every card is held the process waits for one.

The lock files live in ``$KNOCKGS_GPU_LOCKS`` or, by default, a folder of the user's in the
system's temporary directory. An explicit ``"cuda:N"`` claims nothing: jobs naming it share
that card, as before.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from .errors import InputError

try:
    import fcntl
except ImportError:  # not POSIX: no claims, the first card is taken
    fcntl = None

__all__ = ["LOCKS_ENV", "claim_slot", "default_lock_dir", "release_all"]

#: environment variable naming the folder of the GPU lock files
LOCKS_ENV = "KNOCKGS_GPU_LOCKS"

# the open lock files of this process's claims (key -> file object): held until exit
_HELD: dict[str, object] = {}


def default_lock_dir() -> Path:
    """``$KNOCKGS_GPU_LOCKS``, or ``knockgs-gpu-locks-<uid>`` in the system's temporary directory."""
    env = os.environ.get(LOCKS_ENV)
    if env:
        return Path(env)
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"knockgs-gpu-locks-{uid}"


def _lock_name(key: str) -> str:
    """A file name for the card ``key`` (a UUID or a bus id): letters, digits, '-', '_', '.'."""
    return "gpu-" + "".join(c if c.isalnum() or c in "-_." else "_" for c in key) + ".lock"


def _try_lock(key: str, folder: Path) -> bool:
    """Take the exclusive lock of ``key`` without waiting; True when this process now holds it."""
    if key in _HELD:
        return True
    fh = open(folder / _lock_name(key), "a+")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        return False
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    _HELD[key] = fh
    return True


def claim_slot(
    keys: Sequence[str],
    *,
    lock_dir: Path | str | None = None,
    wait_s: float | None = None,
    poll_s: float = 0.5,
    log: Callable[[str], None] | None = None,
) -> int:
    """Claim one of the cards ``keys`` (their UUIDs, in ordinal order) for this process.

    Returns the index of the first card no other process holds; this process holds it until it
    exits (a card it already holds is returned again). When all are held, polls every ``poll_s``
    seconds, ``log`` told once, until one is free; raises :class:`TimeoutError` after ``wait_s``
    seconds (None: wait as long as it takes). Without ``fcntl`` (not POSIX) returns 0. Raises
    :class:`~knockgs_core.errors.InputError` (one line, naming the folder) where the lock files
    cannot be kept.
    """
    if not keys:
        raise ValueError("claim_slot: no cards to claim")
    if fcntl is None:
        return 0
    for i, key in enumerate(keys):
        if key in _HELD:
            return i
    folder = Path(lock_dir) if lock_dir is not None else default_lock_dir()
    start = time.monotonic()
    told = False
    while True:
        for i, key in enumerate(keys):
            try:
                folder.mkdir(parents=True, exist_ok=True)
                if _try_lock(key, folder):
                    return i
            except OSError as exc:
                raise InputError(os.fspath(folder), LOCKS_ENV, f"cannot keep GPU lock files there ({exc.strerror or exc}); "
                                 f"set ${LOCKS_ENV} to a writable folder") from None
        if wait_s is not None and time.monotonic() - start >= wait_s:
            raise TimeoutError(f"all {len(keys)} GPUs are held by other processes (lock files in {folder})")
        if log is not None and not told:
            log(f"all {len(keys)} GPUs are held by other processes; waiting for one (lock files in {folder})")
            told = True
        time.sleep(poll_s)


def release_all() -> None:
    """Release this process's claims (tests; a process's claims otherwise end with it)."""
    for fh in _HELD.values():
        fh.close()
    _HELD.clear()
