"""Give freed heap memory back to the operating system (long streamed runs).

numpy's large temporaries of varying size fragment glibc's heap: after glibc raises its mmap threshold
(it does so whenever a large mmapped block is freed), blocks of tens of MB come from the heap and the
freed ones are kept, so the resident size of a process that steps a filter over hours grows with the
variety of its array sizes, not with its data (the streamed particle tracker: 0.5 GB of live data,
1.6 GB resident after 1,300 frames). ``malloc_trim`` returns the free pages; elsewhere (not glibc) this
is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# steps (frames) of a long loop between returns of the heap's free pages (costs nothing measurable)
TRIM_EVERY = 25

_TRIM = None
if sys.platform.startswith("linux"):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _TRIM = _libc.malloc_trim
        _TRIM.argtypes = [ctypes.c_size_t]
        _TRIM.restype = ctypes.c_int
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        _TRIM = None


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc ``malloc_trim(0)``); False where not available."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True
