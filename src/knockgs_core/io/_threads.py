"""Map a function over items on threads, results in the items' order.

The paper profile's rollout files are large (0.2-0.9 GB each): reading them (Parquet decoding)
and most of the NumPy work on them release the GIL, so a job that reads many of them gains
from a few threads on a machine of many cores. Each item's result is the one a serial loop
computes, so the output does not depend on the thread count.
"""

from __future__ import annotations

from typing import Callable, Iterable, TypeVar

from ..errors import InputError

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["ordered_map"]


def ordered_map(fn: Callable[[T], R], items: Iterable[T], *, workers: int = 1) -> list[R]:
    """``[fn(x) for x in items]``, computed by at most ``workers`` threads.

    The first failing item's error (in the items' order) is raised, as a serial loop would
    raise it; items after it may have been computed already. ``workers`` must be an integer
    >= 1; with 1 (or one item) no thread is started.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError("threads", "workers", f"must be an integer >= 1, got {workers!r}")
    items = list(items)
    if workers == 1 or len(items) <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(workers, len(items)), thread_name_prefix="knockgs-map") as pool:
        return list(pool.map(fn, items))
