"""The service process's memory: the figures /api/status reports (RSS, Python's live blocks, threads),
and handing the heap freed by a finished guest back to the system between guests.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading

_libc = None


def _glibc():
    global _libc
    if _libc is None:
        _libc = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL("libc.so.6")
                _libc = libc if hasattr(libc, "malloc_trim") else False  # musl and others have none
            except OSError:
                pass
    return _libc


def release_free_heap() -> bool:
    """Return free heap pages to the system (glibc's `malloc_trim(0)`); False where there is no such call.

    glibc keeps every arena's high-water mark: a take read for a download, a prune or a re-solve leaves
    pages that are free but still resident, and over a season they add up in steps. Called in the gap
    between guests (a few milliseconds), never while a session records."""
    libc = _glibc()
    if not libc:
        return False
    libc.malloc_trim(0)
    return True


def process_memory() -> dict:
    """RSS in MB (from /proc, None elsewhere), Python's allocated blocks and the thread count: RSS that
    rises while the blocks stay flat is the allocator, blocks that rise are objects kept."""
    rss_mb = None
    try:
        with open("/proc/self/statm") as f:
            rss_pages = int(f.read().split()[1])
        rss_mb = rss_pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        pass
    return {"rss_mb": rss_mb, "python_blocks": sys.getallocatedblocks(), "threads": threading.active_count()}
