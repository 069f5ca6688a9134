"""ordered_map: a thread pool's results in the items' order, the first failing item's error."""

from __future__ import annotations

import threading
import time

import pytest

from knockgs_core.io import ordered_map
from knockgs_core.errors import InputError


def test_results_come_in_the_items_order_whatever_finishes_first():
    # later items finish first; the results still follow the items, and several threads ran
    names = set()

    def slow_first(i):
        time.sleep(0.02 * (5 - i))
        names.add(threading.current_thread().name)
        return i * i

    assert ordered_map(slow_first, range(5), workers=3) == [0, 1, 4, 9, 16]
    assert len(names) > 1
    names.clear()
    assert ordered_map(slow_first, range(5), workers=1) == [0, 1, 4, 9, 16]
    assert names == {threading.main_thread().name}


def test_the_first_failing_item_in_order_raises_as_a_serial_loop_would():
    def fails(i):
        if i in (1, 3):
            time.sleep(0.05 if i == 1 else 0.0)  # item 3 fails first in time
            raise ValueError(f"item {i}")
        return i

    for workers in (1, 4):
        with pytest.raises(ValueError, match="item 1"):
            ordered_map(fails, range(5), workers=workers)


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_a_thread_count_that_is_not_a_positive_integer_is_refused(workers):
    with pytest.raises(InputError, match="workers"):
        ordered_map(str, [1, 2], workers=workers)
