"""The service process's memory as /api/status reports it: RSS, Python's live blocks and threads (the
hand-back of freed heap between guests is flockcal/malloc.py's `release_free_heap`).
"""

from __future__ import annotations

import os
import sys
import threading


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
