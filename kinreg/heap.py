"""glibc's heap: large allocations served from it and freed memory kept in it (``mallopt``).

Every array above glibc's mmap threshold (32 MB at most) is otherwise fresh pages from the kernel,
which it zeroes and maps one fault at a time: the planes stage's workers of a 20 M-point run spent
15-25 % of their CPU in page faults (0.3 s with the heap kept), a 100,000-station block adjustment
40 s of 92 s (16 s). Linux with glibc; elsewhere every function here is a no-op.
"""

from __future__ import annotations

import ctypes
import functools
import sys

# mallopt(3) parameters of glibc, and the values give_back_freed_memory leaves behind: those glibc's
# dynamic threshold reaches once a numpy process has freed an array of 32 MB or more (nearly at once).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_AFTER = 32 << 20
_TRIM_THRESHOLD_AFTER = 64 << 20


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt, libc.malloc_trim  # noqa: B018  (glibc has both)
    except (OSError, AttributeError):  # not glibc
        return None
    return libc


def keep_freed_memory() -> bool:
    """Serve large allocations from the heap and keep freed memory in it, so that the next array
    reuses the pages of the last one; the resident memory then stays at its peak. Returns whether
    it was set."""
    libc = _glibc()
    return libc is not None and bool(libc.mallopt(_M_MMAP_THRESHOLD, 1 << 30)
                                     and libc.mallopt(_M_TRIM_THRESHOLD, (1 << 31) - 1))


def give_back_freed_memory() -> None:
    """After :func:`keep_freed_memory`: the thresholds back to ``_MMAP_THRESHOLD_AFTER`` and
    ``_TRIM_THRESHOLD_AFTER`` (the earlier ones are not readable) and the heap's free memory to the
    kernel (``malloc_trim``)."""
    libc = _glibc()
    if libc is None:
        return
    libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_AFTER)
    libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_AFTER)
    libc.malloc_trim(0)
