"""gdiff.parallel.ordered_map: results in input order, state of the caller seen by workers."""

from __future__ import annotations

import os

import numpy as np
import pytest

from gdiff.parallel import fork_available, ordered_map


@pytest.mark.skipif(not fork_available(), reason="needs the fork start method")
def test_ordered_map_keeps_order_and_sees_the_callers_state():
    table = np.arange(100) ** 2  # caller state; the closure is not sent, the workers fork it

    def square_of(i):
        return int(table[i]), os.getpid()

    items = list(range(37))
    out = list(ordered_map(square_of, items, workers=2, chunksize=3))
    assert [v for v, _ in out] == [i * i for i in items]
    pids = {pid for _, pid in out}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2  # ran in the workers


def test_ordered_map_serial_fallbacks():
    calls = []

    def f(x):
        calls.append(x)  # runs here: the list is ours
        return -x

    assert list(ordered_map(f, [3, 1, 2], workers=1)) == [-3, -1, -2]
    assert list(ordered_map(f, [5], workers=2)) == [-5]  # one item: no pool
    assert calls == [3, 1, 2, 5]


@pytest.mark.skipif(not fork_available(), reason="needs the fork start method")
def test_ordered_map_passes_on_a_workers_error():
    def boom(x):
        if x == 4:
            raise ValueError("item 4 is bad")
        return x

    with pytest.raises(ValueError, match="item 4 is bad"):
        list(ordered_map(boom, range(8), workers=2))
