"""The allocator policy `mirage track` sets: freed memory is reused, not faulted in again."""

import os
import platform
import subprocess
import sys

import pytest

# a 20 MB block (a detection's pyramid) allocated and freed, then five more: what stays
# resident after the free (kB) and the page faults of the five
_PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from mirage_cli.runtime import keep_freed_memory
    assert keep_freed_memory()
def rss():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmRSS:"))
before = rss()
a = np.ones(20 << 20, np.uint8); del a
kept = rss() - before
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    a = np.ones(20 << 20, np.uint8); del a
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _probe(mode: str) -> tuple[int, int]:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True
    )
    kept, faults = out.stdout.split()[-2:]
    return int(kept), int(faults)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_freed_blocks_stay_and_come_back_without_page_faults():
    kept, _ = _probe("default")
    assert kept < 5_000  # glibc gives a freed 20 MB block back to the kernel
    kept, faults = _probe("keep")
    assert kept > 15_000 and faults < 20


@pytest.mark.parametrize("env", [None, "1"])
def test_opencv_gets_a_thread_more_than_the_cores_unless_the_user_says(env):
    """The tracker calls OpenCV's parallel code from two threads (issue 15): its pool is one
    above the cores, and a size the user set in OPENCV_FOR_THREADS_NUM is kept."""
    code = (
        "import cv2\n"
        "from mirage_cli.runtime import opencv_threads_for_two_callers as f\n"
        "print(f(), cv2.getNumThreads(), cv2.getNumberOfCPUs())"
    )
    environ = {k: v for k, v in os.environ.items() if k != "OPENCV_FOR_THREADS_NUM"}
    if env is not None:
        environ["OPENCV_FOR_THREADS_NUM"] = env
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environ)
    assert p.returncode == 0, p.stderr
    got, now, cpus = map(int, p.stdout.split())
    assert got == now == (cpus + 1 if env is None else 1)
