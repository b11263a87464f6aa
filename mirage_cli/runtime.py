"""Process-wide settings a video pipeline needs from the C allocator.

OpenCV allocates each detection's image pyramid afresh (an upsampled box is tens of MB)
and frees it again. glibc serves blocks that large straight from the kernel and gives
freed memory back above a small threshold, so every detection paid for the same pages
again: the sample orbit's tracking loop took 525 000-546 000 page faults and 1.5-1.8 s
of kernel time, about an eighth of its CPU. Keeping freed memory in the heap makes that
about 2 000 faults and 0.4 s, for 20-45 MB more resident memory at the peak (the command,
the in-process loop).
"""

from __future__ import annotations

import ctypes

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest on 64-bit: smaller blocks come from the heap
TRIM_THRESHOLD = 256 << 20  # free memory the heap keeps before giving it back

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to reuse freed memory instead of returning it to the kernel
    (once per process). False where the C library has no `mallopt` (macOS, Windows) or
    refuses the values: the allocator's defaults then stay."""
    global _applied
    if _applied is None:
        try:
            mallopt = ctypes.CDLL(None).mallopt
        except (OSError, AttributeError, TypeError):
            _applied = False
        else:
            mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            _applied = bool(
                mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
                and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
            )
    return _applied
