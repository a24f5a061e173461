"""Process memory settings for the stages: freed memory kept for the next allocation.

A training step or a frame allocates and frees the same large temporaries over and over
(per-Gaussian tensors of several MB, the HexPlane samples, image-sized arrays). glibc's
``malloc`` serves every block above its mmap threshold (at most 32 MB, adjusted at run time)
with a fresh ``mmap`` and returns it to the system when freed, so each new block is faulted in
page by page again: system time that grows with the model, and that a caching allocator
(CUDA's, or jemalloc / tcmalloc) avoids. :func:`keep_freed_memory` raises glibc's mmap and
trim thresholds so such blocks come from the heap and stay there once freed. The peak memory
of a stage does not grow (a block is reused, not added); the process just keeps its peak
until it exits. Elsewhere (no glibc) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

log = logging.getLogger("gdiff.memory")

_M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc malloc.h)
_M_MMAP_THRESHOLD = -3
#: blocks up to this size come from the heap; freed memory up to this size is kept
THRESHOLD_BYTES = 1 << 30
_done: bool | None = None


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds to :data:`THRESHOLD_BYTES` (once per process).

    Returns whether the thresholds are set (False where the C library is not glibc)."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, THRESHOLD_BYTES))
    log.debug("glibc mmap/trim thresholds %s", "raised" if _done else "left as they were")
    return _done
