"""Process-wide settings a video pipeline needs from numpy's BLAS, the C allocator and
OpenCV: the one place the command, its workers and the benchmarks take them from.

OpenCV allocates each detection's image pyramid afresh (an upsampled box is tens of MB)
and frees it again. glibc serves blocks that large straight from the kernel and gives
freed memory back above a small threshold, so every detection paid for the same pages
again: the sample orbit's tracking loop took 525 000-546 000 page faults and 1.5-1.8 s
of kernel time, about an eighth of its CPU. Keeping freed memory in the heap makes that
about 2 000 faults and 0.4 s, for 20-45 MB more resident memory at the peak (the command,
the in-process loop).
"""

from __future__ import annotations

import contextlib
import ctypes
import os

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest on 64-bit: smaller blocks come from the heap
TRIM_THRESHOLD = 64 << 20  # free memory the heap keeps before giving it back (256 MB
# held a 1080p run at 704 MB peak, 64 MB at 648 MB, the same frames/s)

_applied: bool | None = None


def blas_in_calling_thread() -> None:
    """numpy's BLAS in the calling thread unless the environment says otherwise; to be
    called before numpy is imported (this module imports nothing that loads it).

    mirage keeps both cores busy with its own threads (decoding ahead, detecting ahead);
    OpenBLAS's spinning helper threads would fight them for the cores over small matrix
    products (sample orbit: 42 -> 62 frames/s without them). An empty value counts as
    unset, as OpenBLAS reads it (sample orbit: 57-65 frames/s with OPENBLAS_NUM_THREADS=
    against 86-92 with 1, interleaved)."""
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        if not os.environ.get(var, "").strip():
            os.environ[var] = "1"


def _mallopt():
    """glibc's `mallopt` (None where the C library has none: macOS, Windows)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to reuse freed memory instead of returning it to the kernel
    (once per process). False where the C library has no `mallopt` (macOS, Windows) or
    refuses the values: the allocator's defaults then stay."""
    global _applied
    if _applied is None:
        mallopt = _mallopt()
        _applied = mallopt is not None and bool(
            mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
            and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
        )
    return _applied


def return_freed_memory() -> bool:
    """The opposite trade for a batch job that allocates and frees hundreds of MB stage by
    stage (`build-model`): blocks of 1 MB and more from the kernel and back to it when
    freed, so the heap does not grow with each stage's leftovers (144 keyframes: 800 ->
    710 MB peak). False where the C library has no `mallopt`."""
    mallopt = _mallopt()
    return mallopt is not None and bool(mallopt(_M_MMAP_THRESHOLD, 1 << 20))


def opencv_threads_for_two_callers() -> int:
    """Size OpenCV's thread pool one above the cores (unless OPENCV_FOR_THREADS_NUM says),
    and return its size.

    The tracker calls OpenCV's parallel code from two threads of its own: Lucas-Kanade on
    the tracking thread while SIFT runs on the detection worker. One pool thread more than
    the cores cut the tracking thread's waits for the worker from 0.67-0.74 to 0.46-0.57 s
    on the sample orbit (2 cores, 6 interleaved pairs: 1.00-1.11x, median 1.04x), with the
    same poses (the sample's and the 4 m orbit's CSVs identical). Processes that run one
    flight per core (`mirage batch`) keep one thread each instead."""
    import cv2

    if not os.environ.get("OPENCV_FOR_THREADS_NUM", "").strip():
        cv2.setNumThreads(cv2.getNumberOfCPUs() + 1)
    return cv2.getNumThreads()


@contextlib.contextmanager
def opencv_one_thread():
    """OpenCV's parallel code on the calling thread alone inside the block, its pool size
    restored after. cv2.calibrateCamera sums over the views in parallel chunks whose order
    varies, so with more threads two calibrations of the same corners differed in the 12th
    digit (sample: 3.9e-12 in K); alone they are the same to the bit, no slower (27 ms)."""
    import cv2

    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(n)
