"""cgags_ros.parallel: tasks split over threads give what one thread gives."""

from __future__ import annotations

import threading
import time

from cgags_ros.parallel import map_ordered
import pytest


@pytest.mark.parametrize('workers', [1, 2, 3, 8])
def test_map_ordered_returns_the_results_in_the_items_order(workers):
    items = list(range(11))
    assert map_ordered(lambda x: x * x, items, workers) == [x * x for x in items]
    assert map_ordered(lambda x: x, [], workers) == []


def test_map_ordered_runs_the_items_on_several_threads():
    seen = set()

    def task(x):
        seen.add(threading.get_ident())
        time.sleep(0.05)  # outside the GIL, as the rivals' refinements are: both threads run
        return x

    assert map_ordered(task, range(4), 2) == [0, 1, 2, 3]
    assert len(seen) == 2


def test_map_ordered_raises_what_a_task_raised_once_the_other_threads_ended():
    ended = []

    def task(x):
        if x == 1:
            raise ValueError('item 1')
        time.sleep(0.02)
        ended.append(x)
        return x

    with pytest.raises(ValueError, match='item 1'):
        map_ordered(task, range(4), 2)
    # the calling thread's share (0, 2) ran to its end; the failing share stopped at item 1
    assert sorted(ended) == [0, 2]
