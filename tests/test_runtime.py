"""The allocator policy `mirage track` sets: freed memory is reused, not faulted in again."""

import platform
import subprocess
import sys

import pytest

# allocate and free a 20 MB block (a detection's pyramid) five times after a first one
_FAULTS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from mirage_cli.runtime import keep_freed_memory
    assert keep_freed_memory()
a = np.ones(20 << 20, np.uint8); del a
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    a = np.ones(20 << 20, np.uint8); del a
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _faults(mode: str) -> int:
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True
    )
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_freed_blocks_are_reused_without_page_faults():
    assert _faults("default") > 100  # glibc gives each freed 20 MB block back
    assert _faults("keep") < 20
