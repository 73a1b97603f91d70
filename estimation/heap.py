"""Handing freed heap memory back to the operating system between pieces of work.

glibc's allocator keeps the memory of freed objects in its heap for reuse and returns it only
from the heap's top; a long run's records grow while temporaries come and go around them, so
the heap fills with free gaps that stay resident: on a 2 h bag 5-7 MB for the EKF alone, ~13 MB
for four estimators (docs/results/secondary_speed.md, session 24). ``trim`` asks glibc to
release those free pages (``malloc_trim(0)``: it madvises the free chunks anywhere in the heap,
no data moves); ~0.3 ms of CPU a call on such a heap. Where the C library has no
``malloc_trim`` (musl, macOS) it does nothing.
"""

from __future__ import annotations

import ctypes


def _malloc_trim():
    try:
        fn = ctypes.CDLL(None).malloc_trim  # the C library this process already runs on
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_TRIM = _malloc_trim()


def trim() -> bool:
    """Return the heap's free pages to the operating system; True if any were."""
    return bool(_TRIM(0)) if _TRIM is not None else False
