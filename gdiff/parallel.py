"""Independent per-item work over CPU processes, results in input order.

The numpy / OpenCV work of a stage's per-frame loop (compare: one pose at a time) runs mostly
on one core. :func:`ordered_map` spreads such a loop over ``workers`` forked processes and
yields the results in the order of the items, so a caller that folds them in order gets the
same result as the serial loop, whatever the number of workers.

Forked workers inherit the caller's state (frames already read, closures), so ``fn`` need not
be picklable; only the items and the results are sent between processes. Where ``fork`` is
not available (Windows, macOS defaults) or ``workers`` is 1, the loop runs in this process.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_FN: Callable | None = None  # the function of the running ordered_map, seen by forked workers


def _call(item):
    return _FN(item)


@contextlib.contextmanager
def _one_thread_each():
    """OpenCV and the BLAS libraries on one thread while the workers are forked, so that each
    worker inherits that (the workers are the parallelism; their own pools would put two
    threads of each worker on every core). Set here, in the parent, and restored after the
    fork: changing a thread pool inside a forked child can deadlock on a lock another thread
    of the parent held at the fork."""
    import cv2
    from threadpoolctl import threadpool_limits

    n_cv = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            yield
    finally:
        cv2.setNumThreads(n_cv)


def fork_available() -> bool:
    return "fork" in mp.get_all_start_methods()


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int = 1,
                chunksize: int = 2) -> Iterator[R]:
    """``map(fn, items)`` over ``workers`` forked processes, results in the order of ``items``.

    ``fn`` runs in a worker forked after this call started (it sees the caller's memory as it
    was then); its results are pickled back. With ``workers <= 1``, fewer than two items, or
    no ``fork`` start method, the items are mapped here, one after the other."""
    items = list(items)
    if workers <= 1 or len(items) < 2 or not fork_available():
        for x in items:
            yield fn(x)
        return
    global _FN
    previous, _FN = _FN, fn
    try:
        ctx = mp.get_context("fork")
        with _one_thread_each():
            pool = ctx.Pool(min(workers, len(items)))
        with pool:
            yield from pool.imap(_call, items, chunksize=max(1, chunksize))
    finally:
        _FN = previous
