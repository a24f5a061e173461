"""gdiff.memory: freed memory kept for the next allocation (glibc)."""

import subprocess
import sys

import pytest

_PROBE = r"""
import resource, sys
import numpy as np
from gdiff.memory import keep_freed_memory
ok = keep_freed_memory() if sys.argv[1] == "keep" else True
np.ones(8 << 20)  # 64 MB, touched and freed once
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    a = np.ones(8 << 20)  # a block of that size again
    del a
print(int(ok), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> tuple[bool, int]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], check=True,
                         capture_output=True, text=True).stdout.split()
    return bool(int(out[0])), int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc settings")
def test_freed_blocks_are_reused_not_faulted_in_again():
    ok, kept = _faults("keep")
    if not ok:
        pytest.skip("the C library is not glibc")
    _, default = _faults("default")
    assert default >= 5 * 32  # each new 64 MB block is faulted in again (2 MB pages at least)
    assert kept <= 0.05 * default  # the freed block is reused
