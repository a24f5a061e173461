"""gdiff.parallel.ordered_map: results in input order, state of the caller seen by workers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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


@pytest.mark.skipif(not fork_available(), reason="needs the fork start method")
def test_workers_forked_after_opencv_and_blas_ran_threads_do_not_hang():
    # OpenCV's and BLAS's thread pools busy in the parent before the fork: a worker that
    # changed a pool (or used one) could wait forever on a lock held at the fork. Run in a
    # fresh interpreter with a time limit, so a hang fails the test instead of the suite.
    code = (
        "import cv2, numpy as np, time\n"
        "from gdiff.parallel import ordered_map\n"
        "img = np.random.default_rng(0).random((2000, 2000)).astype(np.float32)\n"
        "k = np.ones((9, 9), np.uint8)\n"
        "for _ in range(10):\n"
        "    cv2.dilate(img, k); cv2.resize(img, (3000, 3000)); img[:, :64] @ img[:64]\n"
        "time.sleep(0.5)\n"
        "f = lambda i: float(cv2.dilate(img[:300, :300] * i, k).sum()"
        " + (img[:50, :50] @ img[:50, :50]).sum())\n"
        "n = cv2.getNumThreads()\n"
        "out = list(ordered_map(f, range(12), workers=2))\n"
        "assert out == [f(i) for i in range(12)] and cv2.getNumThreads() == n\n"
        "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
