"""glibc's allocator, tuned and trimmed: the one place flockcal reaches into the C library's malloc.
Dask workers set its thresholds back (`roomy_malloc`); the live service hands freed heap back to the
system between guests (`release_free_heap`). Both are no-ops where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import sys

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 << 20  # glibc's largest dynamic threshold on 64-bit
_TRIM_THRESHOLD = 64 << 20

_libc = None


def _glibc():
    """The C library if it is glibc (it has mallopt and malloc_trim), else False; loaded once."""
    global _libc
    if _libc is None:
        _libc = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL("libc.so.6")
                if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim"):  # musl and others lack these
                    _libc = libc
            except OSError:
                pass
    return _libc


def roomy_malloc() -> None:
    """Let numpy's temporaries reuse the heap again in a Dask worker.

    Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_ set (to hand memory back to the OS), and any
    such variable turns off glibc's sliding mmap threshold: every array over 128 KB is then mmapped and
    unmapped, and a fit spends as long in page faults as in arithmetic (measured: 0.5 s of system time and
    290,000 faults per 30 s take, against 0.04 s and 6,000 in one process). Idempotent; glibc only."""
    libc = _glibc()
    if libc:
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)


def release_free_heap() -> bool:
    """Return free heap pages to the system (glibc's `malloc_trim(0)`); False where there is no such call.

    glibc keeps every arena's high-water mark: a take read for a download, a prune or a re-solve leaves
    pages that are free but still resident, and over a season they add up in steps. The service calls it
    in the gap between guests (a few milliseconds), never while a session records."""
    libc = _glibc()
    if not libc:
        return False
    libc.malloc_trim(0)
    return True
